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

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json
import sys
from pathlib import Path

import torch

import _common as C

SCENES = {"bird": "colmap_bird", "cup": "colmap_cup", "fern": "llff_fern/fern", "dtu": "dtu_scan24_monosdf/scan24"}
TREES = ("before", "after")


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


def compare(scene: str, steps: int, cap: int, runs: dict[str, Path], metrics: dict[str, dict]) -> dict:
    before, after = metrics["before"], metrics["after"]
    step_ms = {tree: 1000 * C.logged_step_seconds(runs[tree]) for tree in TREES}
    return {"benchmark": "defaults_before_after", "scene": scene, "steps": steps, "cap": cap,
            "identical": same_model(runs["before"], runs["after"]),
            **{f"{key}_{tree}": round(m[key], 4) for tree, m in (("before", before), ("after", after))
               for key in ("psnr", "ssim", "lpips")},
            "gaussians": after["num_gaussians"], "step_ms_before": round(step_ms["before"], 1),
            "step_ms_after": round(step_ms["after"], 1),
            "step_ratio": round(step_ms["after"] / step_ms["before"], 3)}


def report(out: Path, records: list[dict], info: dict) -> None:
    columns = [("scene", "scene", ""), ("steps", "steps", ","),
               ("same model", "identical", lambda r: "yes" if r["identical"] else "no"),
               ("PSNR before", "psnr_before", ".2f"), ("PSNR after", "psnr_after", ".2f"),
               ("SSIM before", "ssim_before", ".4f"), ("SSIM after", "ssim_after", ".4f"),
               ("LPIPS before", "lpips_before", ".4f"), ("LPIPS after", "lpips_after", ".4f"),
               ("Gaussians", "gaussians", ","), ("ms/step before", "step_ms_before", ".1f"),
               ("ms/step after", "step_ms_after", ".1f"), ("after / before", "step_ratio", ".3f")]
    text = ["# The defaults before and after the clean-up options", "",
            f"Machine: {C.machine_line(info)}. {C.timestamp()}.", "",
            "`mcsplat train SCENE --steps N --cap-max C` with every other option at its default, in the code before "
            "the options (`before`) and in this tree (`after`), one run at a time; 'same model': every parameter of "
            "the final models equal bit for bit; ms/step: from step 100 to the last.", "",
            C.markdown_table(sorted(records, key=lambda r: r["scene"]), columns), ""]
    C.write_text(out / "results.md", "\n".join(text))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--cap-max", type=int, default=30_000,
                        help="the one option given (without it --steps 300 grows to the paper's 1M at once)")
    parser.add_argument("--before-tree", type=Path, default=C.REPO.parent / "before-cleanup",
                        help="a checkout of the code before the options (git worktree add ../before-cleanup 8fbe206)")
    parser.add_argument("--data-root", type=Path, default=C.DATA_ROOT)
    parser.add_argument("--out", type=Path, default=C.RESULTS / "defaults_before_after")
    parser.add_argument("--report", action="store_true", help="only remake the table")
    args = parser.parse_args()
    results = args.out / "results.jsonl"
    records = C.read_jsonl(results)
    if not args.report:
        if not (args.before_tree / "src" / "mcsplat").is_dir():
            sys.exit(f"defaults_before_after: no checkout of the earlier code at {args.before_tree} (--before-tree)")
        C.warn_if_busy()
        done = {(r["scene"], r["steps"]) for r in records}
        for scene in args.scenes:
            if (scene, args.steps) in done:
                continue
            runs = {tree: args.out / "runs" / f"{tree}-{scene}-{args.steps}" for tree in TREES}
            trees = {"before": args.before_tree, "after": C.REPO}
            # Absolute: from a relative path to the same scene the code before trained another model (bird).
            metrics = {tree: train(trees[tree], args.data_root.resolve() / SCENES[scene], runs[tree], args.steps,
                                   args.cap_max) for tree in TREES}
            new = compare(scene, args.steps, args.cap_max, runs, metrics)
            records.append(new)
            C.append_jsonl(results, [new])
            C.emit(new)
    if not records:
        sys.exit("defaults_before_after: no results yet; run the benchmark first")
    report(args.out, records, C.machine())
    print(f"wrote {args.out / 'results.md'}")


if __name__ == "__main__":
    main()
