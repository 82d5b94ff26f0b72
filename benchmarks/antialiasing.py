"""Anti-aliasing (`--antialiased`, Mip-Splatting's 2D filter) by Mip-Splatting's single-scale protocol: train at one
resolution, test at others.

    .venv/bin/python benchmarks/antialiasing.py                     # lego, cup, bird: 3,000 steps at half size
    .venv/bin/python benchmarks/antialiasing.py --scenes lego --steps 1000
    .venv/bin/python benchmarks/antialiasing.py --init-scale 1.0     # both arms from 3DGS's wider initial Gaussians
    .venv/bin/python benchmarks/antialiasing.py --report            # rebuild results.md from results.jsonl

Each scene trains twice with the same options (`--steps` with the scaled schedule, `--cap-max`, the default
initialisation: lego from random points, the real captures from their SfM points), without and with
`--antialiased`, at `--train-downscale` (2: lego at 200x200, the cup at 400x300, the bird at 272x480) into
results/antialiasing/runs/ (git-ignored). Each model is then scored on the test views loaded at four resolutions:
2x the training one (zoom in), the training one, 1/2 and 1/4 (zoom out, where a splat that covered a pixel shrinks
under one and aliasing shows). Recorded per resolution: PSNR, SSIM and LPIPS-VGG over the test views (every 8th of
lego's 200, all of the real captures'). A picture (results/antialiasing/<scene>.png): a test view at 1/4 of the
training resolution, photo / without / with, enlarged without smoothing.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro
from PIL import Image

import _common as C
from framework import Arm, Common

# folder, default cap, test stride
# (The shared fern has only images_8/, so every --downscale up to 8 loads the same 504x378 images: no zoom to test.)
SCENES = {"lego": (C.LEGO, 30_000, 8), "cup": ("colmap_cup", 50_000, 1), "bird": ("colmap_bird", 50_000, 1)}
ZOOMS = (2.0, 1.0, 0.5, 0.25)  # test resolution over the training one
KEY = ("scene", "antialiased", "steps", "train_downscale", "cap_max", "init_scale")


@dataclass(frozen=True)
class Options:
    """Anti-aliasing against none, trained at one resolution and tested at four."""

    scenes: tuple[Literal["bird", "cup", "lego"], ...] = ("lego", "cup", "bird")
    steps: int = 3000
    train_downscale: int = 2
    cap_max: int | None = None
    """Default: 30k for lego, 50k for the captures."""
    init_scale: float | None = None
    """Initial Gaussian scale x the nearest-neighbour distance (default: the strategy's, 0.1)."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    start = "" if options.init_scale is None else f"-init{options.init_scale:g}"
    return [Arm(f"{scene}-{'aa' if antialiased else 'plain'}-{options.steps}{start}",
                {"scene": scene, "antialiased": antialiased, "steps": options.steps,
                 "train_downscale": options.train_downscale, "cap_max": options.cap_max or SCENES[scene][1],
                 "init_scale": options.init_scale},
                {"steps": options.steps, "downscale": options.train_downscale,
                 "cap_max": options.cap_max or SCENES[scene][1], "antialiased": antialiased,
                 "model.init_scale": options.init_scale})
            for scene in options.scenes for antialiased in (False, True)]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    import torch

    from mcsplat.run import trained as trained_run
    from mcsplat.data import load_scene
    from mcsplat.run.evaluation import evaluate
    from mcsplat.train import train

    scene_folder, _, stride = SCENES[arm.labels["scene"]]
    data, out = options.common.data_root / scene_folder, folder / "runs" / arm.name
    config = C.make_config(data=data, out=out, overwrite=True, quiet=True, save_renders=False,
                           threads=options.common.threads, **arm.config)
    metrics = train(config)
    run = trained_run.load(out, torch.device("cpu"))
    figures = {"steps": metrics["steps"], "seconds_per_step": metrics["train_seconds"] / metrics["steps"],
               "gaussians": metrics["num_gaussians"]}
    for zoom in ZOOMS:
        downscale = options.train_downscale / zoom
        if downscale < 1 or downscale != int(downscale):
            continue
        views = load_scene(data, downscale=int(downscale), test_every=config.test_every).test[::stride]
        score = evaluate(run.model, views, run.background, run.sh_degree, torch.device("cpu"), lpips_net="vgg")
        figures[f"x{zoom:g}"] = {"psnr": score.psnr, "ssim": score.ssim, "lpips": score.lpips, "views": score.views,
                                 "size": f"{views[0].camera.width}x{views[0].camera.height}"}
        if zoom == min(ZOOMS):  # the picture's panels, for finish()
            with torch.no_grad():
                image = _render(run, views[0])
            np.savez(folder / "runs" / f"{arm.name}-picture.npz", photo=views[0].image_float().numpy(), render=image)
    return figures


def _render(run, view) -> np.ndarray:
    from mcsplat.render import render
    return render(run.model, view.camera, run.background, run.sh_degree).rgb.clamp(0, 1).numpy()


def finish(arms: list[Arm], options: Options, folder: Path) -> None:
    """Per scene, photo / without / with: one test view at the smallest resolution, each pixel drawn as an 8x8
    block (the default start only)."""
    if options.init_scale is not None:
        return
    for scene in dict.fromkeys(arm.labels["scene"] for arm in arms):
        saved = {arm.labels["antialiased"]: folder / "runs" / f"{arm.name}-picture.npz"
                 for arm in arms if arm.labels["scene"] == scene}
        if set(saved) != {False, True} or not all(path.is_file() for path in saved.values()):
            continue
        without, with_filter = np.load(saved[False]), np.load(saved[True])
        panels = [without["photo"], without["render"], with_filter["render"]]
        gap = np.ones((panels[0].shape[0], 2, 3))
        strip = np.concatenate([p for panel in panels for p in (panel, gap)][:-1], axis=1)
        big = np.kron(strip, np.ones((8, 8, 1)))
        Image.fromarray((big * 255).round().astype(np.uint8)).save(folder / f"{scene}.png")


def _seconds_per_step(row: dict) -> str:
    return f"{row['s/step']:.3f}" + (f" ({row['timing_note']})" if row.get("timing_note") else "")


def report(records: list[dict], folder: Path) -> str:
    rows = []
    for r in records:
        for zoom in ZOOMS:
            at = r.get(f"x{zoom:g}")
            if at is not None:
                rows.append({"scene": r["scene"], "filter": "2D filter" if r["antialiased"] else "none",
                             "init_scale": r.get("init_scale", 0.1),
                             "zoom": f"{zoom:g}x ({at['size']})", "psnr": at["psnr"], "ssim": at["ssim"],
                             "lpips": at["lpips"], "views": at["views"], "steps": r["steps"],
                             "s/step": r["seconds_per_step"], "timing_note": r.get("timing_note")})
    rows.sort(key=lambda row: (row["scene"], row["zoom"], row["init_scale"], row["filter"]))
    columns = [("scene", "scene", ""), ("test resolution", "zoom", ""), ("filter", "filter", ""),
               ("initial scale (x kNN)", "init_scale", "g"),
               ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"), ("LPIPS-VGG", "lpips", ".4f"),
               ("test views", "views", ""), ("steps", "steps", ","), ("s/step", "s/step", _seconds_per_step)]
    return C.results_page("Anti-aliasing: `--antialiased` against none, trained at one resolution, tested at four",
                          "antialiasing.py", rows, columns)


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("antialiasing"))
