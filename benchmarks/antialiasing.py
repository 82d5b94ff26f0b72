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

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json

import numpy as np
import torch
from PIL import Image

import _common as C

# folder, default cap, test stride
# (The shared fern has only images_8/, so every --downscale up to 8 loads the same 504x378 images: no zoom to test.)
SCENES = {"lego": (C.LEGO, 30_000, 8), "cup": ("colmap_cup", 50_000, 1), "bird": ("colmap_bird", 50_000, 1)}
ZOOMS = (2.0, 1.0, 0.5, 0.25)  # test resolution over the training one


def run_arm(scene: str, antialiased: bool, args) -> dict:
    from mcsplat import run_dir
    from mcsplat.config import ModelConfig, TrainConfig
    from mcsplat.data import load_scene
    from mcsplat.evaluation import evaluate
    from mcsplat.train import train

    folder, cap, stride = SCENES[scene]
    data = C.DATA_ROOT / folder
    start = "" if args.init_scale is None else f"-init{args.init_scale:g}"
    out = C.results_dir("antialiasing") / "runs" / f"{scene}-{'aa' if antialiased else 'plain'}-{args.steps}{start}"
    config = TrainConfig(data=data, out=out, overwrite=True, steps=args.steps, downscale=args.train_downscale,
                         cap_max=args.cap_max or cap, antialiased=antialiased, quiet=True, save_renders=False,
                         threads=args.threads, model=ModelConfig(init_scale=args.init_scale))
    metrics = train(config)
    run = run_dir.load(out, torch.device("cpu"))
    record = {"scene": scene, "antialiased": antialiased, "steps": metrics["steps"], "cap_max": config.mcmc.cap_max,
              "train_downscale": args.train_downscale, "seconds_per_step": metrics["train_seconds"] / metrics["steps"],
              "gaussians": metrics["num_gaussians"], "init_scale": config.model.init_scale, "machine": C.machine("cpu")}
    for zoom in ZOOMS:
        downscale = args.train_downscale / zoom
        if downscale < 1 or downscale != int(downscale):
            continue
        views = load_scene(data, downscale=int(downscale), test_every=config.test_every).test[::stride]
        score = evaluate(run.model, views, run.background, run.sh_degree, torch.device("cpu"), lpips_net="vgg")
        record[f"x{zoom:g}"] = {"psnr": score.psnr, "ssim": score.ssim, "lpips": score.lpips, "views": score.views,
                                "size": f"{views[0].camera.width}x{views[0].camera.height}"}
        if zoom == min(ZOOMS):
            with torch.no_grad():
                image = _render(run, views[0])
            record["picture"] = {"view": views[0].name, "photo": views[0].image_float().numpy(), "render": image}
    return record


def _render(run, view) -> np.ndarray:
    from mcsplat.render import render
    return render(run.model, view.camera, run.background, run.sh_degree).rgb.clamp(0, 1).numpy()


def picture(scene: str, records: list[dict]) -> None:
    """Photo, without, with: one test view at the smallest resolution, each pixel drawn as an 8x8 block."""
    by_arm = {r["antialiased"]: r["picture"] for r in records if "picture" in r}
    if set(by_arm) != {False, True}:
        return
    panels = [by_arm[False]["photo"], by_arm[False]["render"], by_arm[True]["render"]]
    gap = np.ones((panels[0].shape[0], 2, 3))
    strip = np.concatenate([p for panel in panels for p in (panel, gap)][:-1], axis=1)
    big = np.kron(strip, np.ones((8, 8, 1)))
    Image.fromarray((big * 255).round().astype(np.uint8)).save(C.results_dir("antialiasing") / f"{scene}.png")


def _seconds_per_step(row: dict) -> str:
    return f"{row['s/step']:.3f}" + (f" ({row['timing_note']})" if row.get("timing_note") else "")


def report(folder) -> None:
    records = C.read_jsonl(folder / "results.jsonl")
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
    C.write_results_page(folder, "Anti-aliasing: `--antialiased` against none, trained at one resolution, tested "
                         "at four", "antialiasing.py", rows, columns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=["lego", "cup", "bird"])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--train-downscale", type=int, default=2)
    parser.add_argument("--cap-max", type=int, default=None, help="default: 30k for lego, 50k for the cup")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--init-scale", type=float, default=None,
                        help="initial Gaussian scale x the nearest-neighbour distance (default: the strategy's, 0.1)")
    parser.add_argument("--report", action="store_true", help="only rebuild results.md")
    args = parser.parse_args()
    folder = C.results_dir("antialiasing")
    if not args.report:
        for scene in args.scenes:
            records = []
            for antialiased in (False, True):
                record = run_arm(scene, antialiased, args)
                records.append(record)
                kept = {k: v for k, v in record.items() if k not in ("machine", "picture")}
                C.emit(kept)
                C.append_jsonl(folder / "results.jsonl", [{**kept, "machine": record["machine"]}])
            if args.init_scale is None:  # the picture shows the default start
                picture(scene, records)
    report(folder)
    print(json.dumps({"results": str(folder / "results.md")}))


if __name__ == "__main__":
    main()
