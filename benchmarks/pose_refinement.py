"""Camera pose refinement (`--pose-opt`) on the cup with its training poses knocked off, and as it is.

    .venv/bin/python benchmarks/pose_refinement.py                  # 3,000 steps at 400x300, cap 50k
    .venv/bin/python benchmarks/pose_refinement.py --steps 1000 --downscale 4
    .venv/bin/python benchmarks/pose_refinement.py --lrs 3e-4       # adds a learning rate (recorded runs are kept)
    .venv/bin/python benchmarks/pose_refinement.py --report         # rebuild results.md from results.jsonl

A copy of the cup in results/pose_refinement/ (git-ignored runs/) has every training image's pose moved, in its
camera's axes, by `--degrees` (1) about a random axis and `--radius-share` (1%) of the scene radius in a random
direction; the test views keep their poses, the reference the scene is scored against. Runs, with the same options
(`--steps` with the scaled schedule, `--cap-max`, SfM points):

    exact              the capture as it is, no refinement
    exact + pose-opt   the capture as it is, refined (should cost nothing)
    perturbed          the moved poses, no refinement
    perturbed + ...    the moved poses, refined at each of `--lrs`

Recorded per run: test PSNR / SSIM / LPIPS-VGG, s/step, and for refined runs the median corrections learned
(degrees, scene radii) and the median cosine between each learned rotation and the one that undoes the perturbation.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

import _common as C

CUP = "colmap_cup"


def perturbed_copy(target: Path, train_names: set[str], degrees: float, radius_share: float,
                   scene_radius: float) -> dict[str, list[float]]:
    """The cup with its training poses moved, as tests/test_pose_refinement.py moves them (tests/helpers.py);
    returns each moved image's rotation vector (radians)."""
    sys.path.insert(0, str(C.REPO / "tests"))
    from helpers import perturbed_cup

    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    moved = perturbed_cup(C.DATA_ROOT, target, train_names, degrees, radius_share, scene_radius,
                          image_folders=("images", "images_4"))
    return {name: omega.tolist() for name, omega in moved.items()}


def run_arm(label: str, data: Path, args, moved: dict | None, lr: float | None) -> dict:
    from mcsplat.config import TrainConfig
    from mcsplat.data import load_scene
    from mcsplat.train import train

    out = C.results_dir("pose_refinement") / "runs" / f"{label}-{args.steps}"
    config = TrainConfig(data=data, out=out, overwrite=True, steps=args.steps, downscale=args.downscale,
                         cap_max=args.cap_max, quiet=True, save_renders=False, threads=args.threads,
                         pose_opt=lr is not None, **({"pose_opt_lr": lr} if lr is not None else {}))
    metrics = train(config)
    record = {"run": label, "pose_opt_lr": lr, "steps": metrics["steps"], "downscale": args.downscale,
              "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"],
              "seconds_per_step": metrics["train_seconds"] / metrics["steps"], "machine": C.machine("cpu")}
    if lr is not None:
        deltas = torch.load(out / "checkpoint.pt", weights_only=True)["poses"]["deltas"].double()
        names = [view.name for view in load_scene(data, downscale=args.downscale).train]
        record["median_rotation_degrees"] = float(deltas[:, :3].norm(dim=1).median()) * 180 / math.pi
        record["median_translation_radii"] = float(deltas[:, 3:].norm(dim=1).median())
        if moved:
            cosines = [float(np.dot(deltas[i, :3].numpy(), -np.array(moved[name]))
                             / (np.linalg.norm(deltas[i, :3].numpy()) * np.linalg.norm(moved[name]) + 1e-30))
                       for i, name in enumerate(names) if name in moved]
            record["median_cosine"] = float(np.median(cosines))
    return record


def report(folder: Path) -> None:
    records = C.read_jsonl(folder / "results.jsonl")
    columns = [("run", "run", ""), ("--pose-opt-lr", "pose_opt_lr", ".0e"), ("steps", "steps", ","),
               ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"), ("LPIPS-VGG", "lpips", ".4f"),
               ("median correction (deg)", "median_rotation_degrees", ".3f"),
               ("median correction (radii)", "median_translation_radii", ".4f"),
               ("cosine with the undoing rotation", "median_cosine", ".2f"), ("s/step", "seconds_per_step", ".3f")]
    C.write_results_page(folder, "Pose refinement: `--pose-opt` on the cup, its training poses moved and as they "
                         "are", "pose_refinement.py", records, columns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--downscale", type=int, default=2)
    parser.add_argument("--cap-max", type=int, default=50_000)
    parser.add_argument("--degrees", type=float, default=1.0)
    parser.add_argument("--radius-share", type=float, default=0.01)
    parser.add_argument("--lrs", type=float, nargs="+", default=[1e-5, 1e-4])
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--rerun", action="store_true", help="train again the runs results.jsonl already holds")
    parser.add_argument("--report", action="store_true", help="only rebuild results.md")
    args = parser.parse_args()
    folder = C.results_dir("pose_refinement")
    if not args.report:
        from mcsplat.config import TrainConfig
        from mcsplat.data import load_scene

        original = C.DATA_ROOT / CUP
        scene = load_scene(original, downscale=args.downscale)
        moved = perturbed_copy(folder / "runs" / "perturbed-cup", {v.name for v in scene.train}, args.degrees,
                               args.radius_share, scene.radius)
        default = TrainConfig.__dataclass_fields__["pose_opt_lr"].default
        arms = [("exact", original, None, None), (f"exact + pose-opt {default:.0e}", original, None, default),
                ("perturbed", folder / "runs" / "perturbed-cup", moved, None)]
        arms += [(f"perturbed + pose-opt {lr:.0e}", folder / "runs" / "perturbed-cup", moved, lr) for lr in args.lrs]
        done = {(r["run"], r["steps"], r["downscale"]) for r in C.read_jsonl(folder / "results.jsonl")} \
            if (folder / "results.jsonl").is_file() else set()
        for label, data, moved_poses, lr in arms:
            if (label, args.steps, args.downscale) in done and not args.rerun:
                continue  # recorded already: the table keeps that record
            record = run_arm(label.replace(" ", "_"), data, args, moved_poses, lr)
            record["run"] = label
            C.emit({k: v for k, v in record.items() if k != "machine"})
            C.append_jsonl(folder / "results.jsonl", [record])
    report(folder)
    print(json.dumps({"results": str(folder / "results.md")}))


if __name__ == "__main__":
    main()
