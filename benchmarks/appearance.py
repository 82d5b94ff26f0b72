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

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import argparse
import json

import _common as C

SCENES = {"bird": "colmap_bird", "cup": "colmap_cup", "fern": "llff_fern/fern", "dtu": "dtu_scan24_monosdf/scan24"}
ARMS = ("none", "affine", "bilateral-grid")


def run_arm(scene: str, appearance: str, args) -> dict:
    from mcsplat.config import TrainConfig
    from mcsplat.train import train

    out = C.results_dir("appearance") / "runs" / f"{scene}-{appearance}-{args.steps}"
    config = TrainConfig(data=C.DATA_ROOT / SCENES[scene], out=out, overwrite=True, steps=args.steps,
                         cap_max=args.cap_max, appearance=appearance, quiet=True, save_renders=False,
                         threads=args.threads)
    metrics = train(config)
    return {"scene": scene, "appearance": appearance, "steps": metrics["steps"], "cap_max": args.cap_max,
            "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics["lpips"],
            "compensated_psnr": metrics["compensated_psnr"], "compensated_ssim": metrics["compensated_ssim"],
            "seconds_per_step": metrics["train_seconds"] / metrics["steps"], "gaussians": metrics["num_gaussians"],
            "machine": C.machine("cpu")}


def report(folder) -> None:
    records = C.read_jsonl(folder / "results.jsonl")
    columns = [("scene", "scene", ""), ("appearance", "appearance", ""), ("steps", "steps", ","),
               ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"), ("LPIPS-VGG", "lpips", ".4f"),
               ("compensated PSNR", "compensated_psnr", ".2f"), ("compensated SSIM", "compensated_ssim", ".4f"),
               ("s/step", "seconds_per_step", ".3f"), ("Gaussians", "gaussians", ",")]
    title = "Exposure compensation: `--appearance affine` and `bilateral-grid` against none"
    C.write_results_page(folder, title, "appearance.py", records, columns)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", choices=sorted(SCENES), default=["cup", "bird", "fern", "dtu"])
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS))
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--cap-max", type=int, default=50_000)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--report", action="store_true", help="only rebuild results.md")
    args = parser.parse_args()
    folder = C.results_dir("appearance")
    if not args.report:
        for scene in args.scenes:
            for appearance in args.arms:
                record = run_arm(scene, appearance, args)
                C.emit({k: v for k, v in record.items() if k != "machine"})
                C.append_jsonl(folder / "results.jsonl", [record])
    report(folder)
    print(json.dumps({"results": str(folder / "results.md")}))


if __name__ == "__main__":
    main()
