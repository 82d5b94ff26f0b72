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

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import torch
from PIL import Image

import _common as C

SCENES = {"cup": "colmap_cup", "bird": "colmap_bird"}
PAINT = np.array([255, 0, 255], dtype=np.uint8)
BLOCK = (0.375, 0.625)  # the block spans this share of the width and of the height (the centre quarter of its area)
PICTURE_VIEWS = 4


def block_slices(height: int, width: int) -> tuple[slice, slice]:
    return (slice(round(BLOCK[0] * height), round(BLOCK[1] * height)),
            slice(round(BLOCK[0] * width), round(BLOCK[1] * width)))


def painted_copy(source: Path, target: Path) -> Path:
    """The scene with the block painted over every image folder's photos and a masks/ folder leaving it out."""
    if (target / "masks").is_dir():
        return target
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source / "sparse", target / "sparse")
    for folder in sorted(p for p in source.iterdir() if p.is_dir() and p.name.startswith("images")):
        (target / folder.name).mkdir(parents=True)
        for photo in sorted(folder.iterdir()):
            pixels = np.array(Image.open(photo).convert("RGB"))
            pixels[block_slices(*pixels.shape[:2])] = PAINT
            Image.fromarray(pixels).save(target / folder.name / photo.name, quality=95)
            if folder.name == "images":
                mask = np.full(pixels.shape[:2], 255, dtype=np.uint8)
                mask[block_slices(*pixels.shape[:2])] = 0
                (target / "masks").mkdir(exist_ok=True)
                Image.fromarray(mask).save(target / "masks" / f"{photo.stem}.png")
    return target


def block_scores(run: Path, original: Path) -> tuple[dict, list[np.ndarray]]:
    """Block PSNR on the train and test views and the magenta score, from the run's final model; and renders."""
    from mcsplat import run_dir
    from mcsplat.data import load_scene
    from mcsplat.render import render

    trained = run_dir.load(run, torch.device("cpu"))
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


def run_arm(scene: str, painted: Path, masks: str, args) -> tuple[dict, list[np.ndarray]]:
    from mcsplat.config import TrainConfig, budget_seconds
    from mcsplat.train import train

    out = C.results_dir("masks") / "runs" / f"{scene}-{masks}"
    config = TrainConfig(data=painted, out=out, overwrite=True, downscale=args.downscale, budget=args.budget,
                         masks=masks, quiet=True, lpips_net="alex", save_renders=False, threads=args.threads)
    metrics = train(config)
    scores, renders = block_scores(out, C.DATA_ROOT / SCENES[scene])
    record = {"scene": scene, "masks": masks, "budget_seconds": budget_seconds(args.budget),
              "downscale": args.downscale, "steps": metrics["steps"], "gaussians": metrics["num_gaussians"],
              "masked_psnr": metrics.get("masked_psnr"), "masked_ssim": metrics.get("masked_ssim"), **scores,
              "machine": C.machine("cpu")}
    return record, renders


def report(folder: Path) -> None:
    records = C.read_jsonl(folder / "results.jsonl")
    columns = [("scene", "scene", ""), ("masks", "masks", ""), ("steps", "steps", ","),
               ("block PSNR train", "train_block_psnr", ".2f"), ("block PSNR test", "test_block_psnr", ".2f"),
               ("magenta (train)", "train_magenta", ".3f"), ("outside PSNR test", "test_outside_psnr", ".2f"),
               ("masked test PSNR (metrics.json)", "masked_psnr", ".2f"), ("Gaussians", "gaussians", ",")]
    C.write_results_page(folder, "Training masks: a block painted over every photo", "masks.py", records, columns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=["cup", "bird"])
    parser.add_argument("--budget", default="5m", help="--budget of each run (default 5m)")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--report", action="store_true", help="only rebuild results.md")
    args = parser.parse_args()
    folder = C.results_dir("masks")
    if not args.report:
        for scene in args.scenes:
            painted = painted_copy(C.DATA_ROOT / SCENES[scene], folder / "runs" / "scenes" / scene)
            rows = []
            for masks in ("auto", "none"):
                record, renders = run_arm(scene, painted, masks, args)
                C.emit({k: v for k, v in record.items() if k != "machine"})
                C.append_jsonl(folder / "results.jsonl", [record])
                rows.append(np.concatenate(renders, axis=1))
            picture = Image.fromarray(np.concatenate(rows, axis=0))
            picture.resize((picture.width // 2, picture.height // 2), Image.Resampling.BOX).save(
                folder / f"{scene}.jpg", quality=85)  # half size: enough to see the paint, light in the repository
    report(folder)
    print(json.dumps({"results": str(folder / "results.md")}))


if __name__ == "__main__":
    main()
