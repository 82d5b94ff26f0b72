"""The defaults before and after the clean-up options (appearance, anti-aliasing, masks, pose refinement, export
limits): the same `mcsplat train SCENE --steps N --cap-max C` in a checkout of the code before them and in this tree,
on every shared real capture at full resolution, compared model for model.

    git worktree add ../before-cleanup 8fbe206
    .venv/bin/python benchmarks/defaults_before_after.py --before-tree ../before-cleanup     # 300 steps, cap 30k
    .venv/bin/python benchmarks/defaults_before_after.py --report        # the table only

None of the options became a default (each costs some capture or lego PSNR where measured; docs/imperfect-captures.md
has the tables), so a run with the defaults should train the same model as before. This checks that it does, bit
for bit at equal steps (every parameter of the final model, compared with torch.equal), and times a step of each
(from step 100 to the last, one run at a time). Equal models at equal steps leave the step time as the only thing a
fixed time budget could see; a --budget table of both would instead measure the planner's run-to-run spread (its
plan follows the measured step times: two runs of one budget differ by up to 1.8 dB on bird at 5 minutes).

Runs are kept under benchmarks/results/defaults_before_after/runs/ (git-ignored) and skipped when done.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

import _common as C
from framework import Arm, Common, NotReady

SCENES = {"bird": "colmap_bird", "cup": "colmap_cup", "fern": "llff_fern/fern", "dtu": "dtu_scan24_monosdf/scan24"}
TREES = ("before", "after")
KEY = ("scene", "steps")


@dataclass(frozen=True)
class Options:
    """The defaults before and after the clean-up options, model for model."""

    scenes: tuple[Literal["bird", "cup", "fern", "dtu"], ...] = tuple(SCENES)
    steps: int = 300
    cap_max: int = 30_000
    """The one option given (without it --steps 300 grows to the paper's 1M at once)."""
    before_tree: Path = C.REPO.parent / "before-cleanup"
    """A checkout of the code before the options (git worktree add ../before-cleanup 8fbe206)."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    return [Arm(f"{scene}-{options.steps}", {"scene": scene, "steps": options.steps, "cap": options.cap_max})
            for scene in options.scenes]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """Both trees' runs of the scene (each reused when finished), compared."""
    if not (options.before_tree / "src" / "mcsplat").is_dir():
        raise NotReady(f"no checkout of the earlier code at {options.before_tree} (--before-tree)")
    scene, steps = arm.labels["scene"], options.steps
    runs = {tree: folder / "runs" / f"{tree}-{scene}-{steps}" for tree in TREES}
    trees = {"before": options.before_tree, "after": C.REPO}
    # Absolute: from a relative path to the same scene the code before trained another model (bird).
    metrics = {tree: train(trees[tree], options.common.data_root.resolve() / SCENES[scene], runs[tree], steps,
                           options.cap_max) for tree in TREES}
    return compare(runs, metrics)


def train(tree: Path, scene: Path, run: Path, steps: int, cap: int) -> dict:
    """`mcsplat train` of `tree` with its defaults for `steps` steps up to `cap` Gaussians; its metrics.json."""
    if not (run / "metrics.json").is_file():
        C.train_with_tree(tree, [str(scene), "--out", str(run), "--steps", str(steps), "--cap-max", str(cap),
                                 "--quiet", "--overwrite", "--no-save-renders", "--lpips-net", "alex"],
                          run.with_suffix(".log"), "defaults_before_after")
    return json.loads((run / "metrics.json").read_text())


def same_model(first: Path, second: Path) -> bool:
    """Every parameter of the two runs' final models equal, bit for bit."""
    a, b = (torch.load(run / "checkpoint.pt", weights_only=True, map_location="cpu")["model"]
            for run in (first, second))
    return a.keys() == b.keys() and all(torch.equal(a[key], b[key]) for key in a)


def compare(runs: dict[str, Path], metrics: dict[str, dict]) -> dict:
    before, after = metrics["before"], metrics["after"]
    step_ms = {tree: 1000 * C.logged_step_seconds(runs[tree]) for tree in TREES}
    return {"identical": same_model(runs["before"], runs["after"]),
            **{f"{key}_{tree}": round(m[key], 4) for tree, m in (("before", before), ("after", after))
               for key in ("psnr", "ssim", "lpips")},
            "gaussians": after["num_gaussians"], "step_ms_before": round(step_ms["before"], 1),
            "step_ms_after": round(step_ms["after"], 1),
            "step_ratio": round(step_ms["after"] / step_ms["before"], 3)}


def report(records: list[dict], folder: Path) -> str:
    columns = [("scene", "scene", ""), ("steps", "steps", ","),
               ("same model", "identical", lambda r: "yes" if r["identical"] else "no"),
               ("PSNR before", "psnr_before", ".2f"), ("PSNR after", "psnr_after", ".2f"),
               ("SSIM before", "ssim_before", ".4f"), ("SSIM after", "ssim_after", ".4f"),
               ("LPIPS before", "lpips_before", ".4f"), ("LPIPS after", "lpips_after", ".4f"),
               ("Gaussians", "gaussians", ","), ("ms/step before", "step_ms_before", ".1f"),
               ("ms/step after", "step_ms_after", ".1f"), ("after / before", "step_ratio", ".3f")]
    last = records[-1]  # its machine and date (records made before the framework have neither: this machine's, now)
    text = ["# The defaults before and after the clean-up options", "",
            f"Machine: {C.machine_line(last.get('machine') or C.machine())}. {last.get('date') or C.timestamp()}.", "",
            "`mcsplat train SCENE --steps N --cap-max C` with every other option at its default, in the code before "
            "the options (`before`) and in this tree (`after`), one run at a time; 'same model': every parameter of "
            "the final models equal bit for bit; ms/step: from step 100 to the last.", "",
            C.markdown_table(sorted(records, key=lambda r: r["scene"]), columns), ""]
    return "\n".join(text)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("defaults_before_after"))
