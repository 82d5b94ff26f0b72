"""Test PSNR / SSIM / LPIPS against wall-clock time: `--budget` against the code as it was before it, on the shared
captures at full resolution.

    .venv/bin/python benchmarks/time_to_quality.py --before-tree ../baseline            # every scene and time
    .venv/bin/python benchmarks/time_to_quality.py --scenes cup --minutes 10 --arms budget
    .venv/bin/python benchmarks/time_to_quality.py --report                             # tables and plots only

Arms, each run a `mcsplat train` in its own process, one at a time (run nothing else on the machine):
    budget   this tree: `mcsplat train SCENE --budget Tm` (steps, cap and coarse to fine planned as it runs)
    before   a checkout of the code before --budget (`--before-tree`, e.g. a git worktree of commit c12ab67): the
             same scene with `--steps S --cap-max C`, the paper's step schedules multiplied by S / 30,000 by hand
             (as the Makefile's demo did), C the count the budget arm ended with at the same time (or, for a time
             the budget arm has not run, at the nearest one), S from the step time at the end of that budget run
             (full size, count C; where there is none, from a short calibration run of the old code), so that the
             run takes about T minutes of training; it waits for the budget arms of its scene, and is left out
             (with a line) without the checkout or a budget run of its scene
    pointless  this tree, `--budget Tm` on a copy of a COLMAP capture as a transforms.json without points: the
             initialisation triangulated from the known poses, against the budget arm's SfM points
    init     this tree, `--budget Tm --model.init auto|random` on a capture that has poses but no points
             (ngp_fruit): points triangulated from the known poses against the random cube the code before it used

Every run is kept (benchmarks/results/time_to_quality/runs/, git-ignored) and skipped when done, and an arm already
recorded is not run again (--rerun runs it): the script resumes where it stopped. Results: results.jsonl, results.md,
quality_vs_time.png.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

import _common as C
from framework import Arm, Common, NotReady, recorded
from mcsplat.data import load_scene
from mcsplat.io.transforms import write_transforms

SCENES = {  # name -> (folder under the shared data, downscale)
    "bird": ("colmap_bird", 1), "cup": ("colmap_cup", 1), "fern": ("llff_fern/fern", 1),
    "dtu": ("dtu_scan24_monosdf/scan24", 1), "lego": (C.LEGO, 1), "ngp_fruit": ("ngp_fruit", 1)}
POINTLESS = ("bird", "cup")  # COLMAP captures made point-less for the triangulation check
INIT_SCENES, INITS = ("ngp_fruit",), ("auto", "random")  # captures without points: the init arm's scenes and inits
LEGO_TEST_STRIDE = 8         # lego's 200 test views: every 8th (25), as budget.py
PAPER_STEPS = 30_000
CALIBRATION_STEPS = 200
ARMS = ("budget", "before", "pointless", "init")
KEY = ("arm", "scene", "minutes")
ROW_KEY = ("run",)  # runs made by hand (budget-repeat, budget-full-at) share an arm, a scene and a time


@dataclass(frozen=True)
class Options:
    """Test quality against wall-clock time: --budget against the code before it."""

    scenes: tuple[Literal[tuple(SCENES)], ...] = tuple(SCENES)
    minutes: tuple[float, ...] = (2.0, 5.0, 10.0, 30.0)
    """Budget arm times."""
    before_minutes: tuple[float, ...] = (10.0, 30.0)
    """Before arm times."""
    pointless_minutes: tuple[float, ...] = (10.0,)
    init_minutes: tuple[float, ...] = (5.0,)
    arms: tuple[Literal[ARMS], ...] = ARMS
    before_tree: Path = C.REPO.parent / "baseline"
    """A checkout of the code before --budget (git worktree add ../baseline c12ab67)."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def jobs(options: Options) -> list[tuple[str, str, float]]:
    """(arm, scene as recorded, minutes) of every run asked for."""
    scenes, chosen = options.scenes, options.arms
    found = [("budget", s, m) for m in options.minutes for s in scenes] if "budget" in chosen else []
    found += [("before", s, m) for m in options.before_minutes for s in scenes] if "before" in chosen else []
    found += [("pointless", f"{s}-pointless", m) for m in options.pointless_minutes for s in scenes
              if s in POINTLESS] if "pointless" in chosen else []
    found += [("init", f"{s}-{init}", m) for m in options.init_minutes for s in scenes if s in INIT_SCENES
              for init in INITS] if "init" in chosen else []
    return found


def arms(options: Options) -> list[Arm]:
    """An arm per run; a before arm waits for its scene's budget arms (it takes the nearest one's count)."""
    def name(arm: str, scene: str, minutes: float) -> str:
        return f"{arm}-{scene}-{minutes:g}m"

    found = jobs(options)
    budget = {scene: tuple(name(*job) for job in found if job[:2] == ("budget", scene)) for _, scene, _ in found}
    return [Arm(name(arm, scene, minutes), {"arm": arm, "scene": scene, "minutes": minutes},
                after=budget[scene] if arm == "before" else ()) for arm, scene, minutes in found]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """Train the arm's run (a finished one is reused); its test figures."""
    kind, scene, minutes = arm.labels["arm"], arm.labels["scene"], arm.labels["minutes"]
    if kind == "before" and not (options.before_tree / "src" / "mcsplat").is_dir():
        raise NotReady(f"no checkout of the earlier code at {options.before_tree} (--before-tree)")
    nearest = nearest_budget_run(recorded("time_to_quality", folder).latest(), scene, minutes) if kind == "before" \
        else None
    if kind == "before" and nearest is None:
        raise NotReady(f"no budget run of {scene} to take the count from")
    work = folder / "runs"
    run_dir = work / arm.name
    started = time.perf_counter()
    source = scene_folder(scene, options.common.data_root, work)
    if kind == "before":
        metrics = before_run(options.before_tree, source, run_dir, minutes, nearest["num_gaussians"], work,
                             Path(nearest["run"]))
    elif kind == "init":
        metrics = budget_run(C.REPO, source, run_dir, minutes, ("--model.init", scene.split("-")[1]))
    else:
        metrics = budget_run(C.REPO, source, run_dir, minutes)
    return dict(figures(metrics, run_dir), wall_clock=round(time.perf_counter() - started))


def run_train(tree: Path, args: list[str], log: Path) -> None:
    C.train_with_tree(tree, args, log, "time_to_quality")


def scene_folder(name: str, data_root: Path, work: Path) -> Path:
    """The scene as the arms train it: lego with every 8th test view; the point-less copies written once."""
    folder, _ = SCENES[base_scene(name)]
    source = data_root / folder
    if name == "lego":
        target = work / "scenes" / "lego-test25"
        if not (target / "transforms_test.json").is_file():
            target.mkdir(parents=True, exist_ok=True)
            for split in ("train", "test"):
                (target / split).unlink(missing_ok=True)
                (target / split).symlink_to(source / split)
            (target / "transforms_train.json").write_text((source / "transforms_train.json").read_text())
            test = json.loads((source / "transforms_test.json").read_text())
            test["frames"] = test["frames"][::LEGO_TEST_STRIDE]
            (target / "transforms_test.json").write_text(json.dumps(test))
        return target
    if name.endswith("-pointless"):
        target = work / "scenes" / name
        if not (target / "transforms.json").is_file():
            scene = load_scene(source, test_every=0)
            write_transforms(scene.train, target / "transforms.json")
        return target
    return source


def base_scene(name: str) -> str:
    """'bird-pointless' or 'ngp_fruit-random' -> the scene's name."""
    return name.split("-")[0]


def metrics_of(run: Path) -> dict | None:
    path = run / "metrics.json"
    return json.loads(path.read_text()) if path.is_file() else None


def budget_run(tree: Path, scene: Path, run: Path, minutes: float, options: tuple[str, ...] = ()) -> dict:
    if metrics_of(run) is None:
        run_train(tree, [str(scene), "--out", str(run), "--budget", f"{minutes:g}m", *options, "--quiet",
                         "--overwrite"], run.with_suffix(".log"))
    return metrics_of(run)


def hand_scaled(steps: int) -> list[str]:
    """The paper's step schedules x steps / 30,000, as options of the code before --scale-schedule."""
    def scaled(value: int) -> str:
        return str(max(1, round(value * steps / PAPER_STEPS)))
    return ["--mcmc.refine-start", scaled(500), "--mcmc.refine-stop", scaled(25_000), "--mcmc.refine-every",
            scaled(100), "--sh-increase-every", scaled(1000)]


def trained_step_seconds(budget_run: Path | None) -> float | None:
    """Seconds per step at the end of a budget run: full size, its final count, a model well into training. A
    short calibration run measures 1.8x less than that on bird (its young Gaussians are smaller), so the before
    arm's steps come from here when the budget arm has run."""
    log = budget_run / "log.jsonl" if budget_run is not None else None
    if log is None or not log.is_file():
        return None
    records = [r for r in map(json.loads, log.read_text().splitlines()) if "loss" in r]
    final = [r for r in records if r.get("resolution") == 1.0 and r["num_gaussians"] == records[-1]["num_gaussians"]]
    if len(final) < 3:
        return None
    first, last = final[-3], final[-1]
    return (last["elapsed_seconds"] - first["elapsed_seconds"]) / (last["step"] - first["step"])


def before_step_seconds(tree: Path, scene: Path, cap: int, work: Path) -> float:
    """Seconds per step of the old code at `cap` Gaussians: a short run that grows to the cap at once."""
    run = work / "calibration" / f"{scene.name}-{cap}"
    if metrics_of(run) is None:
        run.parent.mkdir(parents=True, exist_ok=True)
        run_train(tree, [str(scene), "--out", str(run), "--steps", str(CALIBRATION_STEPS), "--cap-max", str(cap),
                         "--model.num-init-points", str(max(1, cap // 2)), "--mcmc.refine-start", "2",
                         "--mcmc.refine-every", "2", "--mcmc.refine-stop", str(CALIBRATION_STEPS), "--quiet",
                         "--overwrite", "--no-save-renders", "--lpips-net", "alex"], run.with_suffix(".log"))
    return C.logged_step_seconds(run)  # records at steps 100 and 200: the second half runs at the cap


def before_run(tree: Path, scene: Path, run: Path, minutes: float, cap: int, work: Path,
               budget_run: Path | None = None) -> dict:
    if metrics_of(run) is None:
        step_seconds = trained_step_seconds(budget_run) or before_step_seconds(tree, scene, cap, work)
        steps = max(100, int(60 * minutes / step_seconds))
        run_train(tree, [str(scene), "--out", str(run), "--steps", str(steps), "--cap-max", str(cap),
                         "--model.num-init-points", str(max(1, cap // 2)), "--quiet", "--overwrite",
                         *hand_scaled(steps)], run.with_suffix(".log"))
    return metrics_of(run)


def figures(metrics: dict, run: Path) -> dict:
    return {"psnr": round(metrics["psnr"], 3), "ssim": round(metrics["ssim"], 4),
            "lpips": round(metrics["lpips"], 4) if metrics.get("lpips") is not None else None,
            "steps": metrics["steps"], "num_gaussians": metrics["num_gaussians"],
            "train_seconds": metrics["train_seconds"], "wall_seconds": metrics.get("wall_seconds"),
            "run": str(run)}


def nearest_budget_run(records: list[dict], scene: str, minutes: float) -> dict | None:
    """The budget arm's record at `minutes`, or at the nearest time it ran (log scale): the before arm takes its
    count and its step time."""
    ran = [r for r in records if r["arm"] == "budget" and r["scene"] == scene]
    if not ran:
        return None
    return min(ran, key=lambda r: abs(math.log(r["minutes"] / minutes)))


# ------------------------------------------------------------------------------------------------ the report
def report(records: list[dict], folder: Path) -> str:
    columns = [("scene", "scene", ""), ("arm", "arm", ""), ("minutes", "minutes", "g"), ("PSNR", "psnr", ".2f"),
               ("SSIM", "ssim", ".4f"), ("LPIPS", "lpips", ".4f"), ("steps", "steps", ","),
               ("Gaussians", "num_gaussians", ","), ("train s", "train_seconds", ".0f")]
    ordered = sorted(records, key=lambda r: (r["scene"], r["arm"], r["minutes"]))
    lines = ["# Test quality against wall-clock time", "",
             f"Machine: {C.machine_line(C.machine())}. {C.timestamp()}.", "",
             "`budget`: `mcsplat train SCENE --budget Tm`; `before`: the code before it with --steps fitted to the "
             "time and the schedules scaled by hand, at the count the budget arm reached; `pointless`: the budget "
             "arm on the capture as a transforms.json without points (triangulated from the known poses); `init`: "
             "the budget arm on a capture without points, initialised by `--model.init auto` (triangulated) or "
             "`random` (the cube the code before it used); `budget-capped`: `--budget Tm --cap-max N`, run by hand "
             "(each record's note has its command); `budget-repeat`: other runs of a budget arm, kept for the spread "
             "between runs of one budget (each record's note says which run and code); `budget-standin`: the budget "
             "arm with a calibration tried and not kept (the record's note says what it did); `budget-full-at`: "
             "`--budget Tm --resolution-full-at F`, full size reached at F of the run instead of 0.4 (the scene's "
             "label says F, the record's note the command).", "",
             C.markdown_table(ordered, columns), ""]
    lines += target_lines(records)
    plot(folder, records)
    return "\n".join(lines) + "\n"


def target_lines(records: list[dict]) -> list[str]:
    """The issue's target: --budget 10m at least the before arm's 30-minute PSNR, scene by scene."""
    lines = ["## --budget 10m against the code before it at 30 minutes", ""]
    for scene in sorted({r["scene"] for r in records}):
        new = [r for r in records if r["scene"] == scene and r["arm"] == "budget" and r["minutes"] == 10]
        old = [r for r in records if r["scene"] == scene and r["arm"] == "before" and r["minutes"] == 30]
        if new and old:
            gap = new[0]["psnr"] - old[0]["psnr"]
            lines.append(f"- {scene}: {new[0]['psnr']:.2f} dB in 10 min against {old[0]['psnr']:.2f} dB in 30 min "
                         f"({gap:+.2f} dB): {'met' if gap >= 0 else 'missed'}")
    return lines


def plot(out: Path, records: list[dict]) -> None:
    plt = C.pyplot()
    if plt is None:
        return
    from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter
    scenes = sorted({base_scene(r["scene"]) for r in records})
    fig, axes = plt.subplots(1, len(scenes), figsize=(4 * len(scenes), 3.4), squeeze=False)
    styles = {"budget": ("tab:blue", "o", "--budget"), "before": ("tab:gray", "s", "before (--steps)"),
              "pointless": ("tab:orange", "^", "--budget, no points"),
              "init": ("tab:green", "v", "--budget, no points (auto / random init)"),
              "budget-repeat": ("tab:blue", "x", "--budget, run again"),
              "budget-full-at": ("tab:purple", "D", "--budget, full size at F (0.4 default)")}
    annotated = {"init": lambda r: r["scene"].split("-")[1], "budget-full-at": lambda r: r["scene"].split("-full")[1]}
    for ax, scene in zip(axes[0], scenes):
        for arm, (color, marker, label) in styles.items():
            rows = sorted((r for r in records if r["arm"] == arm and base_scene(r["scene"]) == scene),
                          key=lambda r: r["train_seconds"])
            if rows:  # at the minutes each run trained (a before run may overrun its planned time)
                ax.plot([r["train_seconds"] / 60 for r in rows], [r["psnr"] for r in rows], marker=marker,
                        color=color, label=label, linestyle="-" if arm in ("budget", "before", "pointless") else "none")
            for r in rows if arm in annotated else ():  # several variants at one time: named, not joined
                ax.annotate(annotated[arm](r), (r["train_seconds"] / 60, r["psnr"]), fontsize=7,
                            xytext=(4, 0), textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(FixedLocator([2, 5, 10, 20, 30, 40]))  # minutes, not 10^x
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_title(scene)
        ax.set_xlabel("minutes of training")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("test PSNR (dB)")
    named = {}  # every arm in one legend, whichever panel drew it
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            named.setdefault(label, handle)
    axes[0][-1].legend(named.values(), named.keys(), fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "quality_vs_time.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("time_to_quality"))
