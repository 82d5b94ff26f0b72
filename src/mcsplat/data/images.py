"""Image files: which folder to read, sizes from the headers, and parallel decoding into uint8 RGB tensors; float
images back to uint8 pixels for a file, a video or a page."""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from ..errors import DataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".webp", ".bmp", ".tif", ".tiff")
# Shrinking is area averaging (what a camera with bigger pixels would record; no ringing on sharp edges, unlike
# LANCZOS): exact sums for integer factors, Pillow's BOX filter in float mode otherwise.
RESAMPLE = Image.Resampling.BOX

Size = tuple[int, int]  # (width, height)
ALPHA_MODES = ("RGBA", "LA", "La", "RGBa", "PA")


def image_dirs(root: Path) -> dict[int, Path]:
    """The image folders of a scene, by downscale factor: images/ -> 1, images_4/ -> 4."""
    found: dict[int, Path] = {}
    if (root / "images").is_dir():
        found[1] = root / "images"
    for entry in root.iterdir():
        match = re.fullmatch(r"images_(\d+)", entry.name)
        if match and entry.is_dir() and int(match.group(1)) >= 1:
            found[int(match.group(1))] = entry
    return found


def choose_image_dir(root: Path, downscale: int) -> tuple[Path, int]:
    """The folder to read for `downscale` N and the factor its images already have.

    images_N/ if it exists, else images/ (resized by 1/N), else the images_M/ with the largest M <= N (resized by
    M/N); when every images_M/ is smaller than asked (M > N), the one closest to the requested size, used as is.
    """
    dirs = image_dirs(root)
    if downscale in dirs:
        return dirs[downscale], downscale
    if 1 in dirs:
        return dirs[1], 1
    if not dirs:
        raise DataError(f"no image folder in {root}: expected images/ (or images_N/ for a downscaled copy)")
    below = [m for m in dirs if m <= downscale]
    factor = max(below) if below else min(dirs)
    return dirs[factor], factor


def downscaled_size(width: int, height: int, factor: float) -> Size:
    """Size of a width x height image shrunk by `factor` (rounded, at least 1 pixel)."""
    return max(1, round(width / factor)), max(1, round(height / factor))


def find_image(path: Path) -> Path | None:
    """`path` if it exists, else the same stem with a usual image suffix (for file paths given without one)."""
    if path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES:
        candidate = path.with_name(path.name + suffix)
        if candidate.is_file():
            return candidate
    return None


def probe_size(path: Path) -> Size:
    """(width, height) from the file header; DataError if the file is missing or not an image."""
    if not path.is_file():
        raise DataError(f"image file is missing: {path}")
    try:
        with Image.open(path) as im:
            return im.size
    except Exception as exc:  # PIL raises UnidentifiedImageError, OSError, SyntaxError, ValueError ...
        raise DataError(f"cannot read image {path}: {_reason(exc)}; replace the file or remove it from the "
                        "scene") from None


def probe_sizes(paths: Sequence[Path]) -> list[Size]:
    return [probe_size(p) for p in paths]


def has_alpha(path: Path) -> bool:
    """Whether the image file carries an alpha channel (from its header: the pixels are not decoded)."""
    with Image.open(path) as im:
        return im.mode in ALPHA_MODES or (im.mode == "P" and "transparency" in im.info)


def uint8_pixels(image: torch.Tensor) -> np.ndarray:
    """uint8 numpy pixels of a float image in [0, 1] (any shape, any device): clamped, times 255, rounded half up.

    The one conversion of every picture mcsplat writes or shows (renders, video frames, the viewer's modes, the mesh's
    pictures), so that they agree to the bit; View.image_float goes the other way."""
    return (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def load_images(paths: Sequence[Path], sizes: Sequence[Size], background: Sequence[float],
                workers: int | None = None) -> list[torch.Tensor]:
    """Decode every image to uint8 [H, W, 3], resized to `sizes[i]` (width, height) when it differs, with any alpha
    channel composited on `background` (RGB in [0, 1]). Decoding runs in a thread pool (PIL releases the GIL)."""
    if len(paths) != len(sizes):
        raise ValueError("load_images needs one size per path")
    workers = workers or min(8, os.cpu_count() or 1)
    bg = np.asarray(background, dtype=np.float32) * 255.0
    if workers <= 1 or len(paths) <= 1:
        return [_load_one(p, s, bg) for p, s in zip(paths, sizes)]
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcsplat-decode")
    try:
        futures = [pool.submit(_load_one, p, s, bg) for p, s in zip(paths, sizes)]
        return [f.result() for f in futures]
    finally:
        # On an error, do not decode the rest of a large scene before reporting it.
        pool.shutdown(wait=True, cancel_futures=True)


def _load_one(path: Path, size: Size, background: np.ndarray) -> torch.Tensor:
    try:
        with Image.open(path) as im:
            im.load()
            array = np.asarray(_to_rgb_or_rgba(im))
    except FileNotFoundError:
        raise DataError(f"image file is missing: {path}") from None
    except Exception as exc:
        raise DataError(f"cannot decode image {path}: {_reason(exc)}; replace the file or remove it from the "
                        "scene") from None
    height, width, channels = array.shape
    if (width, height) == tuple(size):
        if channels == 3:
            return torch.from_numpy(np.array(array, dtype=np.uint8))  # a writable copy owned by the tensor
        alpha = array[:, :, 3:4].astype(np.float32) * (1.0 / 255.0)
        rgb = array[:, :, :3].astype(np.float32) * alpha + background * (1.0 - alpha)
    elif channels == 3:
        rgb = _area_resize(array, size)
    else:
        # Average premultiplied colour and alpha over each output pixel, then composite: the same as compositing
        # at full resolution and averaging, so transparent pixels do not darken the edges.
        premultiplied = array[:, :, :3].astype(np.uint16) * array[:, :, 3:4]
        colour = _area_resize(premultiplied, size) * (1.0 / 255.0)
        alpha = _area_resize(array[:, :, 3:4], size) * (1.0 / 255.0)
        rgb = colour + background * (1.0 - alpha)
    return torch.from_numpy(np.clip(np.rint(rgb), 0, 255).astype(np.uint8))


def _area_resize(array: np.ndarray, size: Size) -> np.ndarray:
    """Area-average an integer [H, W, C] array down to size (width, height), in float64, rounded only by the caller.

    Pillow's 8-bit resize rounds after each of its two passes, which brightens by up to one level; this does not.
    """
    height, width, channels = array.shape
    out_width, out_height = size
    if height % out_height == 0 and width % out_width == 0:
        fy, fx = height // out_height, width // out_width
        sums = np.zeros((out_height, out_width, channels), dtype=np.uint64 if fx * fy > 65536 else np.uint32)
        for dy in range(fy):  # fx*fy strided adds of output-sized arrays: exact, and fast
            for dx in range(fx):
                sums += array[dy::fy, dx::fx]
        return sums / float(fx * fy)
    out = np.empty((out_height, out_width, channels), dtype=np.float64)
    for c in range(channels):  # Pillow's float mode keeps full precision; one channel at a time bounds the memory
        plane = Image.fromarray(np.ascontiguousarray(array[:, :, c], dtype=np.float32), "F")
        out[:, :, c] = np.asarray(plane.resize((out_width, out_height), RESAMPLE))
    return out


def _to_rgb_or_rgba(im: Image.Image) -> Image.Image:
    mode = im.mode
    if mode in ("RGB", "RGBA"):
        return im
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        # 16-bit grey: keep the top 8 bits (PIL's convert("RGB") would clip instead of scaling).
        grey = (np.asarray(im, dtype=np.float64) / (257.0 if mode != "I" else 1.0))
        grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
        return Image.fromarray(np.repeat(grey[:, :, None], 3, axis=2), "RGB")
    if mode in ALPHA_MODES or (mode == "P" and "transparency" in im.info):
        return im.convert("RGBA")
    return im.convert("RGB")


def _reason(exc: BaseException) -> str:
    if isinstance(exc, UnidentifiedImageError):
        return "not an image file that Pillow can read"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]
