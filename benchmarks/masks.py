"""Training masks on a real capture: a block painted over every photo, trained with its mask and without.

    .venv/bin/python benchmarks/masks.py                           # cup and bird, full resolution, --budget 5m each
    .venv/bin/python benchmarks/masks.py --scenes cup --budget 2m --downscale 4
    .venv/bin/python benchmarks/masks.py --report                  # rebuild results.md from results.jsonl

Each scene is copied into results/masks/runs/ (git-ignored) with a magenta block painted over the same quarter of
every photo (the centre: it covers the object, which the other views see) and a masks/ folder that leaves the block
out. It then trains twice with the same options, `--masks auto` (the masks/ folder) and `--masks none`, and scores
each run's renders against the photos as they were before the paint:

    block PSNR       PSNR of the block region of the render against the unpainted photo, on the training views
                     (where the paint was) and on the test views
    magenta          how magenta the block region of the training renders is: mean of (R + B) / 2 - G, 1 for the
                     paint, about 0 for the scene
    outside PSNR     PSNR of the rest of the render against the photo, on the test views (the mean over the
                     views, as the test PSNR is; for the masked run it matches its own masked PSNR in metrics.json,
                     up to the JPEG re-encoding of the painted photos)

A picture per scene (results/masks/<scene>.jpg): training renders with the mask (top) and without (bottom).
"""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import tyro
from PIL import Image

import _common as C
from framework import Arm, Common

SCENES = {"cup": "colmap_cup", "bird": "colmap_bird"}
PAINT = np.array([255, 0, 255], dtype=np.uint8)
BLOCK = (0.375, 0.625)  # the block spans this share of the width and of the height (the centre quarter of its area)
PICTURE_VIEWS = 4
KEY = ("scene", "masks", "budget_seconds", "downscale")


@dataclass(frozen=True)
class Options:
    """Training masks: a block painted over every photo, trained with its mask and without."""

    scenes: tuple[Literal["bird", "cup"], ...] = ("cup", "bird")
    budget: str = "5m"
    """--budget of each run."""
    downscale: int = 1
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def block_slices(height: int, width: int) -> tuple[slice, slice]:
    return (slice(round(BLOCK[0] * height), round(BLOCK[1] * height)),
            slice(round(BLOCK[0] * width), round(BLOCK[1] * width)))


def painted_copy(source: Path, target: Path) -> Path:
    """The scene with the block painted over every image folder's photos and a masks/ folder leaving it out (made
    once, aside, then renamed: the arms of a scene may run at the same time)."""
    if (target / "masks").is_dir():
        return target
    building = target.with_name(f"{target.name}.{os.getpid()}.tmp")
    shutil.rmtree(building, ignore_errors=True)
    shutil.copytree(source / "sparse", building / "sparse")
    for folder in sorted(p for p in source.iterdir() if p.is_dir() and p.name.startswith("images")):
        (building / folder.name).mkdir(parents=True)
        for photo in sorted(folder.iterdir()):
            pixels = np.array(Image.open(photo).convert("RGB"))
            pixels[block_slices(*pixels.shape[:2])] = PAINT
            Image.fromarray(pixels).save(building / folder.name / photo.name, quality=95)
            if folder.name == "images":
                mask = np.full(pixels.shape[:2], 255, dtype=np.uint8)
                mask[block_slices(*pixels.shape[:2])] = 0
                (building / "masks").mkdir(exist_ok=True)
                Image.fromarray(mask).save(building / "masks" / f"{photo.stem}.png")
    if not (target / "masks").is_dir():
        shutil.rmtree(target, ignore_errors=True)
        building.replace(target)
    shutil.rmtree(building, ignore_errors=True)
    return target


def block_scores(run: Path, original: Path) -> tuple[dict, list[np.ndarray]]:
    """Block PSNR on the train and test views and the magenta score, from the run's final model; and renders."""
    from mcsplat.run import trained as trained_run
    from mcsplat.data import load_scene
    from mcsplat.render import render

    trained = trained_run.load(run, torch.device("cpu"))
    clean = load_scene(original, downscale=trained.config.downscale, test_every=trained.config.test_every)
    photos = {view.name: view for view in clean.train + clean.test}
    scores, renders = {}, []
    for split, views in (("train", trained.scene.train), ("test", trained.scene.test)):
        errors, magenta, outside_errors = [], [], []
        for view in views:
            with torch.no_grad():
                image = render(trained.model, view.camera, trained.background, trained.sh_degree).rgb.clamp(0, 1)
            block = block_slices(*image.shape[:2])
            region = image[block]
            photo = photos[view.name].image_float()
            errors.append(float(((region - photo[block]) ** 2).mean()))
            outside = torch.ones(image.shape[:2], dtype=torch.bool)
            outside[block] = False
            outside_errors.append(float(((image[outside] - photo[outside]) ** 2).mean()))
            magenta.append(float(((region[..., 0] + region[..., 2]) / 2 - region[..., 1]).mean()))
            if split == "train" and len(renders) < PICTURE_VIEWS and len(errors) % 10 == 1:
                renders.append((image.numpy() * 255).astype(np.uint8))
        scores[f"{split}_block_psnr"] = round(float(-10 * np.log10(np.mean(errors))), 3)
        scores[f"{split}_magenta"] = round(float(np.mean(magenta)), 3)
        scores[f"{split}_outside_psnr"] = round(float(np.mean([-10 * np.log10(e) for e in outside_errors])), 3)
    return scores, renders


def arms(options: Options) -> list[Arm]:
    from mcsplat.config import budget_seconds

    return [Arm(f"{scene}-{masks}", {"scene": scene, "masks": masks, "budget_seconds": budget_seconds(options.budget),
                                     "downscale": options.downscale},
                {"downscale": options.downscale, "budget": options.budget, "masks": masks})
            for scene in options.scenes for masks in ("auto", "none")]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    from mcsplat.train import train

    scene = arm.labels["scene"]
    original = options.common.data_root / SCENES[scene]
    painted = painted_copy(original, folder / "runs" / "scenes" / scene)
    out = folder / "runs" / arm.name
    metrics = train(C.make_config(data=painted, out=out, overwrite=True, quiet=True, lpips_net="alex",
                                  save_renders=False, threads=options.common.threads, **arm.config))
    scores, renders = block_scores(out, original)
    Image.fromarray(np.concatenate(renders, axis=1)).save(folder / "runs" / f"{arm.name}-renders.png")
    return {"steps": metrics["steps"], "gaussians": metrics["num_gaussians"],
            "masked_psnr": metrics.get("masked_psnr"), "masked_ssim": metrics.get("masked_ssim"), **scores}


def finish(arms: list[Arm], options: Options, folder: Path) -> None:
    """A picture per scene whose two arms have renders: with the mask (top), without (bottom), at half size (enough
    to see the paint, light in the repository)."""
    for scene in dict.fromkeys(arm.labels["scene"] for arm in arms):
        strips = [folder / "runs" / f"{scene}-{masks}-renders.png" for masks in ("auto", "none")]
        if all(strip.is_file() for strip in strips):
            picture = Image.fromarray(np.concatenate([np.array(Image.open(strip)) for strip in strips], axis=0))
            picture.resize((picture.width // 2, picture.height // 2), Image.Resampling.BOX).save(
                folder / f"{scene}.jpg", quality=85)


def report(records: list[dict], folder: Path) -> str:
    columns = [("scene", "scene", ""), ("masks", "masks", ""), ("steps", "steps", ","),
               ("block PSNR train", "train_block_psnr", ".2f"), ("block PSNR test", "test_block_psnr", ".2f"),
               ("magenta (train)", "train_magenta", ".3f"), ("outside PSNR test", "test_outside_psnr", ".2f"),
               ("masked test PSNR (metrics.json)", "masked_psnr", ".2f"), ("Gaussians", "gaussians", ",")]
    return C.results_page("Training masks: a block painted over every photo", "masks.py", records, columns)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("masks"))
