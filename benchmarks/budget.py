"""Quality at equal budget (the paper's Fig. 3 at our scale): MCMC against ADC with the same hard cap.

    .venv/bin/python benchmarks/budget.py                                   # lego: caps 10k/30k/100k x mcmc/adc,
                                                                            # then bird (SfM init) at 30k
    .venv/bin/python benchmarks/budget.py --steps 3000 --caps 10000 --strategies mcmc --sfm-scene none
    .venv/bin/python benchmarks/budget.py --caps --sfm-scene bird           # only the SfM run
    .venv/bin/python benchmarks/budget.py --report                          # rebuild table and plot, train nothing

Each run is mcsplat.train.train() with a TrainConfig: same steps, seed, initial points and cap for both strategies
(ADC stops densifying at the cap: config.adc.cap_max), each strategy with its own initial scales and opacities (ADC
3DGS's 1.0 x kNN and 0.1, MCMC 0.1 x kNN and 0.5) and ADC resetting opacities at its first densification step on
lego's white background, as the paper ran its 3DGS baseline. The records in results.jsonl made before 2026-11-25
used the baseline as it was then: MCMC's initial Gaussians and no reset at the first densification step. Lego (NeRF-Synthetic 400x400, white background) starts from the random
init; the SfM scene from its COLMAP points. Prints one JSON line per run, appends it to
benchmarks/results/budget/results.jsonl, and rewrites results.md (table and verdict) and budget.png (PSNR / SSIM /
LPIPS against the cap, log x) from the latest record of every configuration. Runs live under results/budget/runs/
(git-ignored): a finished run is reused, an interrupted one resumed from its checkpoint (--rerun starts afresh).

Short CPU runs: the paper's schedules, in steps (MCMC refine 500..25000 every 100, ADC densify 500..15000 every 100,
opacity reset every 3000, SH degree +1 every 1000), are multiplied by --schedule-scale (default steps / 30000), so the
default 1200-step run refines every 4 steps from step 20 to 1000. The position learning rate always decays over --steps.

Initial points (random init): the paper starts from 100k points, but MCMC only grows from its initial count (5% per
refine step) and prunes down to the cap at the first refine step when it starts above it, so 100k points would make
the 10k and 30k budgets a prune-then-relocate experiment. The default is half the budget, min(100k, cap / 2): both
strategies start from the same cap/2 points and have room to grow to the cap (MCMC reaches it after 15 refine steps).
--init-points N fixes the count instead.

Evaluation: lego has 200 test views; LPIPS-VGG on CPU costs ~1 s a view, so by default every 8th test view is used
(25 views; --test-stride 1 for all). The SfM scene is evaluated on its whole test split (every 8th image).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import contextlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

import _common as C
import mcsplat.run_dir as run_folders
from mcsplat.train import train
from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.strategy.adc import ADCConfig
from mcsplat.strategy.mcmc import MCMCConfig

PAPER_STEPS = 30_000
PAPER_INIT_POINTS = 100_000


@dataclass
class Schedule:
    """The paper's step schedules multiplied by `scale` (at least 1 step each)."""

    scale: float

    def _s(self, steps: int) -> int:
        return max(1, round(steps * self.scale))

    def values(self) -> dict:
        return {"refine_start": self._s(500), "refine_stop": self._s(25_000), "refine_every": self._s(100),
                "densify_start": self._s(500), "densify_stop": self._s(15_000), "densify_every": self._s(100),
                "reset_every": self._s(3000), "sh_increase_every": self._s(1000)}


@dataclass
class Job:
    scene: str            # short name (lego, bird, cup or the folder's name)
    path: Path
    init: str             # random or sfm
    strategy: str
    cap: int
    downscale: int
    test_stride: int
    max_test_views: int

    def name(self, steps: int, scale: float) -> str:
        return f"{self.scene}-{self.init}-{self.strategy}-cap{C.human(self.cap)}-{steps}steps-x{scale:g}"


@contextlib.contextmanager
def test_subset(stride: int, max_views: int):
    """Evaluate train()'s final metrics on every `stride`-th test view (at most max_views; 0 = all): wraps the
    scene loader the run calls. Training views are untouched."""
    original = run_folders.load_scene

    def load_with_subset(*args, **kwargs):
        scene = original(*args, **kwargs)
        views = scene.test[::stride]
        scene.test = views[:max_views] if max_views else views
        return scene

    run_folders.load_scene = load_with_subset
    try:
        yield
    finally:
        run_folders.load_scene = original


def init_points(cap: int, fixed: int | None) -> int:
    return fixed if fixed else min(PAPER_INIT_POINTS, max(1, cap // 2))


def make_config(job: Job, args, run_dir: Path, resume: bool, overwrite: bool) -> TrainConfig:
    sched = Schedule(args.schedule_scale).values()
    return TrainConfig(
        data=job.path, out=run_dir, strategy=job.strategy, cap_max=job.cap, steps=args.steps, downscale=job.downscale,
        device=args.device, seed=args.seed, threads=args.threads, quiet=True, lpips_net="vgg", save_renders=False,
        save_every=max(1, args.steps // 10), resume=resume, overwrite=overwrite,
        scale_schedule=False,  # the schedules below are already multiplied by --schedule-scale
        sh_increase_every=sched["sh_increase_every"],
        model=ModelConfig(init=job.init, num_init_points=init_points(job.cap, args.init_points)),
        mcmc=MCMCConfig(refine_start=sched["refine_start"], refine_stop=sched["refine_stop"],
                        refine_every=sched["refine_every"], relocation="paper"),  # the paper's MCMC, grown to the cap
        adc=ADCConfig(densify_start=sched["densify_start"], densify_stop=sched["densify_stop"],
                      densify_every=sched["densify_every"], reset_every=sched["reset_every"]))


def run_job(job: Job, args, runs: Path, info: dict) -> tuple[dict, bool]:
    """(record, whether it is new). Reuses a finished run, resumes an interrupted one."""
    run_dir = runs / job.name(args.steps, args.schedule_scale)
    finished = (run_dir / "metrics.json").is_file()
    started = time.perf_counter()
    if finished and not args.rerun:
        metrics, fresh = json.loads((run_dir / "metrics.json").read_text()), False
    else:
        resume = run_folders.RunDir(run_dir).checkpoint_file.is_file() and not args.rerun
        config = make_config(job, args, run_dir, resume=resume, overwrite=args.rerun or finished)
        with test_subset(job.test_stride, job.max_test_views):
            metrics, fresh = train(config), True
    record = {
        "strategy": job.strategy, "cap": job.cap, "steps": metrics["steps"], "psnr": round(metrics["psnr"], 3),
        "ssim": round(metrics["ssim"], 4),
        "lpips": round(metrics["lpips"], 4) if metrics.get("lpips") is not None else None,
        "num_gaussians": metrics["num_gaussians"], "train_seconds": metrics["train_seconds"],
        "benchmark": "budget", "scene": job.scene, "init": job.init, "schedule_scale": args.schedule_scale,
        "init_points": init_points(job.cap, args.init_points) if job.init == "random" else None,
        "lpips_net": metrics.get("lpips_net"), "exported_gaussians": metrics.get("exported_gaussians"),
        "ms_per_step": round(1000.0 * metrics["train_seconds"] / max(1, metrics["steps"]), 1),
        "test_views": metrics.get("test_views"), "test_stride": job.test_stride, "downscale": job.downscale,
        "device": metrics.get("device"), "threads": args.threads or torch.get_num_threads(),
        "schedule": Schedule(args.schedule_scale).values(), "run_dir": str(run_dir),
        "reused": not fresh,
    }
    if fresh:
        record.update(wall_seconds=round(time.perf_counter() - started, 1), machine=info, commit=C.git_commit(),
                      date=C.timestamp())
    return record, fresh


# ------------------------------------------------------------------------------------------------ the reports
def config_key(r: dict) -> tuple:
    return r["scene"], r["init"], r["strategy"], r["cap"], r["steps"], r["schedule_scale"]


def latest(records: list[dict]) -> list[dict]:
    """The last record of every configuration, sorted by scene, steps, cap and strategy."""
    by_key = {}
    for r in records:
        if r.get("benchmark") == "budget":
            by_key[config_key(r)] = r
    return sorted(by_key.values(), key=lambda r: (r["scene"] != "lego", r["scene"], r["steps"], r["cap"],
                                                  r["strategy"]))


def gaps(rows: list[dict]) -> list[tuple[int, float, dict, dict]]:
    """(cap, MCMC PSNR - ADC PSNR, mcmc row, adc row) for every cap with both strategies, smallest cap first."""
    out = []
    for cap in sorted({r["cap"] for r in rows}):
        pair = {r["strategy"]: r for r in rows if r["cap"] == cap}
        if "mcmc" in pair and "adc" in pair:
            out.append((cap, pair["mcmc"]["psnr"] - pair["adc"]["psnr"], pair["mcmc"], pair["adc"]))
    return out


def verdict(rows: list[dict]) -> list[str]:
    """The paper's claim, checked on one scene/steps group: MCMC >= ADC at every budget, the gap growing as the
    budget shrinks."""
    g = gaps(rows)
    if not g:
        return ["- not enough runs for a verdict (need both strategies at a cap)"]
    lines = ["- PSNR gap MCMC - ADC: " + ", ".join(f"{C.human(cap)}: {gap:+.2f} dB" for cap, gap, _, _ in g)]
    all_ahead = all(gap >= 0 for _, gap, _, _ in g)
    lines.append(f"- MCMC >= ADC (PSNR) at every budget: **{'yes' if all_ahead else 'no'}**")
    for metric, better in (("ssim", 1), ("lpips", -1)):
        ok = all(m.get(metric) is not None and a.get(metric) is not None and better * (m[metric] - a[metric]) >= 0
                 for _, _, m, a in g)
        lines.append(f"- MCMC at least as good in {metric.upper()} at every budget: {'yes' if ok else 'no'}")
    if rows[0]["scene"] == "lego":
        lines.append("- lego is evidence neither way: the paper's limited-budget figure averages real scenes only "
                     "(NeRF-Synthetic left out as \"highly saturated\"), and short runs with scaled schedules squeeze "
                     "ADC's opacity resets together")
    if len(g) >= 2:
        values = [gap for _, gap, _, _ in g]  # smallest cap first
        if all(x >= y for x, y in zip(values, values[1:])) and values[0] > values[-1]:
            trend = "yes"
        elif all(x <= y for x, y in zip(values, values[1:])) and values[0] < values[-1]:
            trend = "no; the gap shrinks as the budget shrinks"
        else:
            trend = "no; not monotone in the budget"
        lines.append(f"- gap grows as the budget shrinks: **{trend}** ({values[0]:+.2f} dB at {C.human(g[0][0])} vs "
                     f"{values[-1]:+.2f} dB at {C.human(g[-1][0])})")
    return lines


def markdown(rows: list[dict]) -> str:
    cols = [("scene", "scene", ""), ("init", "init", lambda r: r["init"] + (f" ({C.human(r['init_points'])})"
                                                                             if r.get("init_points") else "")),
            ("strategy", "strategy", ""), ("cap", "cap", lambda r: C.human(r["cap"])), ("steps", "steps", ""),
            ("sched. scale", "schedule_scale", ".4g"), ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"),
            ("LPIPS-vgg", "lpips", ".4f"), ("final #G", "num_gaussians", ""), ("test views", "test_views", ""),
            ("train min", "train_seconds", lambda r: f"{r['train_seconds'] / 60:.1f}"),
            ("ms/step", "ms_per_step", ".0f"), ("threads", "threads", ""), ("device", "device", "")]
    machines = sorted({C.machine_line(r["machine"]) for r in rows if r.get("machine")})
    lines = ["# Quality at equal budget: MCMC vs ADC", "",
             "Same steps, initial points, seed and hard cap for both strategies; schedules scaled by the schedule "
             "scale (see budget.py). Random init: min(100k, cap/2) points unless noted. Runs before 2026-11-25 used "
             "the old ADC baseline (MCMC's initial Gaussians, no reset at the first densification).", "",
             "Machine: " + ("; ".join(machines) or "-"), "", C.markdown_table(rows, cols), ""]
    groups = sorted({(r["scene"] != "lego", r["scene"], r["steps"], r["schedule_scale"]) for r in rows})
    for _, scene, steps, scale in groups:
        group = [r for r in rows if (r["scene"], r["steps"], r["schedule_scale"]) == (scene, steps, scale)]
        lines += [f"## {scene}, {steps} steps (schedule x{scale:g})", ""] + verdict(group) + [""]
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> bool:
    plt = C.pyplot()
    lego = [r for r in rows if r["init"] == "random"]
    if plt is None or not lego:
        return False
    def group_of(r):
        return r["scene"], r["steps"], r["schedule_scale"]
    counts = {}
    for r in lego:  # the group with the most runs (the last one on a tie) is plotted
        counts[group_of(r)] = counts.get(group_of(r), 0) + 1
    scene, steps, scale = max(counts, key=lambda g: (counts[g], list(counts).index(g)))
    group = [r for r in lego if group_of(r) == (scene, steps, scale)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    metrics = (("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("lpips", "LPIPS-vgg (lower is better)"))
    for ax, (metric, label) in zip(axes, metrics):
        for strategy, style in (("mcmc", "o-"), ("adc", "s--")):
            pts = sorted((r["cap"], r[metric]) for r in group
                         if r["strategy"] == strategy and r.get(metric) is not None)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, label=strategy.upper())
        if metric == "psnr":
            for cap, gap, m, _ in gaps(group):
                ax.annotate(f"{gap:+.2f}", (cap, m["psnr"]), textcoords="offset points", xytext=(0, 7),
                            ha="center", fontsize=8)
        ax.set_xscale("log")
        caps = sorted({r["cap"] for r in group})
        ax.set_xticks(caps, [C.human(c) for c in caps])
        ax.minorticks_off()
        ax.margins(x=0.1, y=0.15)
        ax.set_xlabel("budget (max Gaussians)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{scene}, random init, {steps} steps (schedules x{scale:g}): MCMC vs ADC at equal budget",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def report(out: Path) -> None:
    rows = latest(C.read_jsonl(out / "results.jsonl"))
    C.write_text(out / "results.md", markdown(rows))
    plotted = plot(rows, out / "budget.png")
    print(f"wrote {out / 'results.md'}" + (f" and {out / 'budget.png'}" if plotted else ""), file=sys.stderr)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="lego", help="random-init scene: lego (shared data) or a folder")
    parser.add_argument("--caps", type=int, nargs="*", default=[10_000, 30_000, 100_000],
                        help="budgets for the random-init scene (none: skip it)")
    parser.add_argument("--strategies", nargs="+", choices=("mcmc", "adc"), default=["mcmc", "adc"])
    parser.add_argument("--steps", type=int, default=1200,
                        help="steps per run (1200: 6-15 min per run on 2 cores, 100k cap included)")
    parser.add_argument("--schedule-scale", type=float, default=None,
                        help="multiplies the paper's schedules (default: steps / 30000)")
    parser.add_argument("--init-points", type=int, default=0, help="random-init points (0: min(100k, cap/2))")
    parser.add_argument("--test-stride", type=int, default=8, help="evaluate every N-th test view of --scene")
    parser.add_argument("--max-test-views", type=int, default=0, help="at most this many test views (0: no limit)")
    parser.add_argument("--sfm-scene", default="bird", help="bird, cup, a COLMAP folder, or none")
    parser.add_argument("--sfm-caps", type=int, nargs="+", default=[30_000], help="budgets for the SfM scene")
    parser.add_argument("--sfm-downscale", type=int, default=2, help="bird is 544x960; 2 gives 272x480")
    parser.add_argument("--sfm-test-stride", type=int, default=1)
    parser.add_argument("--data-root", default=str(C.DATA_ROOT))
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: all cores)")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rerun", action="store_true", help="train again even when a finished run exists")
    parser.add_argument("--report", action="store_true", help="only rebuild results.md and budget.png")
    parser.add_argument("--out", default=None, help="results folder (default benchmarks/results/budget)")
    args = parser.parse_args()
    if args.schedule_scale is None:
        args.schedule_scale = round(args.steps / PAPER_STEPS, 6)
    if args.device == "cuda" and not args.report:
        C.cuda_or_exit("cuda", "budget")
    out = Path(args.out) if args.out else C.results_dir("budget")
    out.mkdir(parents=True, exist_ok=True)
    if args.report:
        report(out)
        return
    C.warn_if_busy()

    def short_name(scene: str) -> str:
        return scene if scene == "lego" or scene in C.SFM_SCENES else Path(scene).name

    jobs = [Job(short_name(args.scene), C.scene_path(args.scene, args.data_root), "random", s, cap, 1,
                args.test_stride, args.max_test_views) for cap in args.caps for s in args.strategies]
    if args.sfm_scene and args.sfm_scene.lower() != "none":
        jobs += [Job(short_name(args.sfm_scene), C.scene_path(args.sfm_scene, args.data_root), "sfm", s,
                     cap, args.sfm_downscale, args.sfm_test_stride, 0) for cap in args.sfm_caps for s in args.strategies]
    for job in jobs:
        if not job.path.exists():
            sys.exit(f"scene folder {job.path} not found (pass --data-root or a path)")
    info = C.machine(args.device)
    runs = out / "runs"
    for job in jobs:
        record, fresh = run_job(job, args, runs, info)
        C.emit({k: v for k, v in record.items() if k not in ("machine", "schedule")})
        known = {(r.get("run_dir"), r.get("train_seconds")) for r in C.read_jsonl(out / "results.jsonl")}
        if fresh or (record["run_dir"], record["train_seconds"]) not in known:  # a reused run missing from the file
            C.append_jsonl(out / "results.jsonl", [record])
    report(out)


if __name__ == "__main__":
    main()
