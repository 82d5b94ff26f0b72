"""Regenerate data/lego_demo/, the small demo scene bundled with the repository.

It is a subset of the NeRF-synthetic "lego" scene at 400x400 (shared/data/nerf_synthetic_lego_400/lego):
all 100 train views and every 8th test view (r_0, r_8, ..., r_192: 25 views), shrunk to 200x200 RGBA PNG by 2x2 area
averaging of premultiplied colour (so the transparent background does not bleed into the edges) in floating point,
rounded once (Pillow's 8-bit resize rounds after each pass and brightens by up to one level), with
transforms_train.json / transforms_test.json rewritten to list exactly those frames. camera_angle_x and the poses are
copied unchanged (the focal length in pixels follows the image width).

    python scripts/make_demo_scene.py [--source PATH] [--output PATH]
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SOURCE = REPO.parent / "shared" / "data" / "nerf_synthetic_lego_400" / "lego"
DEFAULT_OUTPUT = REPO / "data" / "lego_demo"
SIZE = 200
TEST_EVERY = 8


def shrink(source: Path, target: Path) -> None:
    """Area-average an RGBA image by an integer factor with premultiplied alpha, rounding once at the end."""
    with Image.open(source) as image:
        if image.mode != "RGBA":
            raise SystemExit(f"{source} is {image.mode}, expected RGBA")
        rgba = np.asarray(image).astype(np.float64)
    factor = rgba.shape[0] // SIZE
    if rgba.shape[:2] != (SIZE * factor, SIZE * factor):
        raise SystemExit(f"{source} is {rgba.shape[1]}x{rgba.shape[0]}, expected a multiple of {SIZE}")
    alpha = rgba[:, :, 3:] / 255.0
    blocks = np.concatenate([rgba[:, :, :3] * alpha, alpha], axis=2)
    mean = blocks.reshape(SIZE, factor, SIZE, factor, 4).mean(axis=(1, 3))
    out_alpha = mean[:, :, 3:]
    colour = np.divide(mean[:, :, :3], out_alpha, out=np.zeros_like(mean[:, :, :3]), where=out_alpha > 0)
    out = np.concatenate([colour, out_alpha * 255.0], axis=2)
    target.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.clip(np.rint(out), 0, 255).astype(np.uint8), "RGBA").save(target, optimize=True)


def subset(source: Path, output: Path, split: str, every: int) -> int:
    meta = json.loads((source / f"transforms_{split}.json").read_text())
    frames = meta["frames"][::every]
    for frame in frames:
        relative = frame["file_path"].removeprefix("./") + ".png"
        shrink(source / relative, output / relative)
    meta["frames"] = frames
    (output / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2) + "\n")
    return len(frames)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=DEFAULT_SOURCE, help="the lego folder at 400x400")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args()
    if not (args.source / "transforms_train.json").is_file():
        raise SystemExit(f"{args.source} is not the lego scene (no transforms_train.json)")
    for split in ("train", "test"):  # start clean, keep SOURCE.md
        shutil.rmtree(args.output / split, ignore_errors=True)
    args.output.mkdir(parents=True, exist_ok=True)
    train = subset(args.source, args.output, "train", 1)
    test = subset(args.source, args.output, "test", TEST_EVERY)
    size = sum(p.stat().st_size for p in args.output.rglob("*") if p.is_file())
    print(f"wrote {args.output}: {train} train + {test} test views, {SIZE}x{SIZE}, {size / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
