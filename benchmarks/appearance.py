"""Exposure compensation (`--appearance affine|bilateral-grid`) on every shared real capture: with and without.

    .venv/bin/python benchmarks/appearance.py                       # bird, cup, fern, DTU; 3,000 steps, cap 50k
    .venv/bin/python benchmarks/appearance.py --scenes cup --steps 1000 --arms none bilateral-grid
    .venv/bin/python benchmarks/appearance.py --report              # rebuild results.md from results.jsonl

Each scene trains once per arm at full resolution with the same options (`--steps` with the scaled schedule,
`--cap-max`, from its SfM points; DTU, which has none, from its triangulated points): `--appearance none`, `affine`
and `bilateral-grid`, into results/appearance/runs/ (git-ignored). Recorded from each run's metrics.json:

    plain        test PSNR / SSIM / LPIPS-VGG over whole views, no transform (what a viewer shows)
    compensated  3DGS's train_test_exp protocol: each test view's colour transform fitted on its left half (least
                 squares, the scene frozen), its right half scored; computed for every arm alike
    s/step       training seconds per step (an affine transform adds a 3x3 matrix product per pixel, a grid its
                 slicing)
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

import _common as C
from framework import Arm, Common

SCENES = {"bird": "colmap_bird", "cup": "colmap_cup", "fern": "llff_fern/fern", "dtu": "dtu_scan24_monosdf/scan24"}
ARMS = ("none", "affine", "bilateral-grid")
KEY = ("scene", "appearance", "steps", "cap_max")


@dataclass(frozen=True)
class Options:
    """Exposure compensation against none on the shared captures."""

    scenes: tuple[Literal["bird", "cup", "dtu", "fern"], ...] = ("cup", "bird", "fern", "dtu")
    arms: tuple[Literal["none", "affine", "bilateral-grid"], ...] = ARMS
    steps: int = 3000
    cap_max: int = 50_000
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    return [Arm(f"{scene}-{appearance}-{options.steps}",
                {"scene": scene, "appearance": appearance, "steps": options.steps, "cap_max": options.cap_max},
                {"steps": options.steps, "cap_max": options.cap_max, "appearance": appearance})
            for scene in options.scenes for appearance in options.arms]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    from mcsplat.train import train

    config = C.make_config(data=options.common.data_root / SCENES[arm.labels["scene"]], out=folder / "runs" / arm.name,
                           overwrite=True, quiet=True, save_renders=False, threads=options.common.threads, **arm.config)
    metrics = train(config)
    return {"steps": metrics["steps"], "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"],
            "compensated_psnr": metrics["compensated_psnr"], "compensated_ssim": metrics["compensated_ssim"],
            "seconds_per_step": metrics["train_seconds"] / metrics["steps"], "gaussians": metrics["num_gaussians"]}


def report(records: list[dict], folder: Path) -> str:
    columns = [("scene", "scene", ""), ("appearance", "appearance", ""), ("steps", "steps", ","),
               ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"), ("LPIPS-VGG", "lpips", ".4f"),
               ("compensated PSNR", "compensated_psnr", ".2f"), ("compensated SSIM", "compensated_ssim", ".4f"),
               ("s/step", "seconds_per_step", ".3f"), ("Gaussians", "gaussians", ",")]
    title = "Exposure compensation: `--appearance affine` and `bilateral-grid` against none"
    return C.results_page(title, "appearance.py", records, columns)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("appearance"))
