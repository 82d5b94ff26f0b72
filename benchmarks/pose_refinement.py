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

import json
import math
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

import _common as C
from framework import Arm, Common

CUP = "colmap_cup"
KEY = ("run", "steps", "downscale")


@dataclass(frozen=True)
class Options:
    """Pose refinement on the cup, its training poses moved and as they are."""

    steps: int = 3000
    downscale: int = 2
    cap_max: int = 50_000
    degrees: float = 1.0
    """Each training pose is turned by this much about a random axis ..."""
    radius_share: float = 0.01
    """... and moved by this share of the scene radius in a random direction."""
    lrs: tuple[float, ...] = (1e-5, 1e-4)
    """--pose-opt-lr of the refined runs on the moved poses."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    from mcsplat.pose_refinement import PoseOptions

    default = PoseOptions().pose_opt_lr
    runs = [("exact", False, None), (f"exact + pose-opt {default:.0e}", False, default), ("perturbed", True, None)]
    runs += [(f"perturbed + pose-opt {lr:.0e}", True, lr) for lr in options.lrs]
    return [Arm(f"{label.replace(' ', '_')}-{options.steps}",
                {"run": label, "pose_opt_lr": lr, "steps": options.steps, "downscale": options.downscale,
                 "perturbed": perturbed},
                {"steps": options.steps, "downscale": options.downscale, "cap_max": options.cap_max,
                 "pose_opt": lr is not None, **({"pose_opt_lr": lr} if lr is not None else {})})
            for label, perturbed, lr in runs]


def perturbed_copy(options: Options, target: Path) -> dict[str, list[float]]:
    """The cup with its training poses moved, as tests/training/test_pose_refinement.py moves them
    (tests/support/helpers.py), made once for these --degrees and --radius-share; each moved image's rotation vector
    (radians)."""
    from mcsplat.data import load_scene

    asked = {"degrees": options.degrees, "radius_share": options.radius_share, "downscale": options.downscale}
    made = target / "moved.json"
    if made.is_file() and json.loads(made.read_text())["asked"] == asked:
        return json.loads(made.read_text())["moved"]
    sys.path.insert(0, str(C.REPO / "tests" / "support"))
    from helpers import perturbed_cup

    scene = load_scene(options.common.data_root / CUP, downscale=options.downscale)
    building = target.with_name(f"{target.name}.{os.getpid()}.tmp")
    shutil.rmtree(building, ignore_errors=True)
    building.mkdir(parents=True)
    moved = perturbed_cup(options.common.data_root, building, {v.name for v in scene.train}, options.degrees,
                          options.radius_share, scene.radius, image_folders=("images", "images_4"))
    moved = {name: omega.tolist() for name, omega in moved.items()}
    (building / "moved.json").write_text(json.dumps({"asked": asked, "moved": moved}))
    shutil.rmtree(target, ignore_errors=True)
    building.replace(target)
    return moved


def run(arm: Arm, options: Options, folder: Path) -> dict:
    import torch

    from mcsplat.data import load_scene
    from mcsplat.train import train

    data, moved = options.common.data_root / CUP, None
    if arm.labels["perturbed"]:
        data = folder / "runs" / "perturbed-cup"
        moved = perturbed_copy(options, data)
    out = folder / "runs" / arm.name
    config = C.make_config(data=data, out=out, overwrite=True, quiet=True, save_renders=False,
                           threads=options.common.threads, **arm.config)
    metrics = train(config)
    figures = {"steps": metrics["steps"], "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"],
               "seconds_per_step": metrics["train_seconds"] / metrics["steps"]}
    if arm.labels["pose_opt_lr"] is not None:
        deltas = torch.load(out / "checkpoint.pt", weights_only=True)["poses"]["deltas"].double()
        names = [view.name for view in load_scene(data, downscale=options.downscale).train]
        figures["median_rotation_degrees"] = float(deltas[:, :3].norm(dim=1).median()) * 180 / math.pi
        figures["median_translation_radii"] = float(deltas[:, 3:].norm(dim=1).median())
        if moved:
            cosines = [float(np.dot(deltas[i, :3].numpy(), -np.array(moved[name]))
                             / (np.linalg.norm(deltas[i, :3].numpy()) * np.linalg.norm(moved[name]) + 1e-30))
                       for i, name in enumerate(names) if name in moved]
            figures["median_cosine"] = float(np.median(cosines))
    return figures


def report(records: list[dict], folder: Path) -> str:
    columns = [("run", "run", ""), ("--pose-opt-lr", "pose_opt_lr", ".0e"), ("steps", "steps", ","),
               ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"), ("LPIPS-VGG", "lpips", ".4f"),
               ("median correction (deg)", "median_rotation_degrees", ".3f"),
               ("median correction (radii)", "median_translation_radii", ".4f"),
               ("cosine with the undoing rotation", "median_cosine", ".2f"), ("s/step", "seconds_per_step", ".3f")]
    return C.results_page("Pose refinement: `--pose-opt` on the cup, its training poses moved and as they are",
                          "pose_refinement.py", records, columns)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("pose_refinement"))
