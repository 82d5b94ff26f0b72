"""Training masks: which pixels of each image the loss learns from and the masked metrics score.

A mask is a greyscale image per photo in the scene's masks/ folder (or the folder --masks names), named after the
photo as Brush and nerfstudio name them (`masks/<view name>.png`, the view name being the image's path without its
suffix, or just `<image stem>.png`) or as COLMAP does (`masks/<image file name>.png`). A nonzero pixel is kept and a
zero pixel left out (--invert-masks swaps the two); --masks alpha takes the images' own alpha channel instead, as a
soft weight.

A mask goes through what its image goes through: undistorted with the image's camera when the camera has lens
distortion, then area-averaged to the size the image is loaded at, so that a mask pixel lies on its image pixel.
Masks stay in memory as uint8 [H, W] keep weights (255: kept), a third of the images' size.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from PIL import Image

from mcsplat.data import images
from mcsplat.errors import DataError

MASK_FOLDER = "masks"
NOTE_PREFIX = "masks for"  # how the Scene note on masks starts (the console repeats it when a run starts)
ASPECT_TOLERANCE = 0.01  # a mask may be stored at another size than its image, not at another shape


@dataclass(frozen=True)
class MaskOptions:
    """Where a scene's masks come from: "auto" (SCENE/masks/ when it exists), "none", "alpha" or a folder."""

    source: str = "auto"
    invert: bool = False

    def __post_init__(self) -> None:
        if not self.source.strip():
            raise DataError(f"--masks {self.source!r} names no folder: give 'auto', 'none', 'alpha' or the folder "
                            "that holds one mask PNG per image")
        if self.invert and self.source == "none":
            raise DataError("--invert-masks with --masks none: there are no masks to invert; leave one of them out")

    def folder(self, root: Path) -> Path | None:
        """The mask folder to read, or None (no masks, or the alpha channel)."""
        if self.source in ("none", "alpha"):
            return None
        if self.source == "auto":
            folder = root / MASK_FOLDER
            return folder if folder.is_dir() else None
        folder = Path(self.source).expanduser()
        if not folder.is_dir():
            raise DataError(f"--masks {self.source}: no such folder; give the folder that holds one mask PNG per "
                            "image, or --masks none")
        return folder


@dataclass(frozen=True)
class MaskJob:
    """One image's mask: the file it is read from, the size it must be resized to before the camera's undistortion
    (the image file's size), the undistortion (a data.undistort.Job, or None) and the size it is loaded at."""

    source: Path
    file_size: images.Size
    undistort: object | None
    size: images.Size
    alpha: bool  # the source is the image itself and its alpha channel is the mask


def mask_file(folder: Path, view_name: str, image: Path) -> Path | None:
    """The mask of the image `image` (view `view_name`) in `folder`, under any of the accepted names."""
    candidates = [folder / f"{view_name}.png", folder / f"{image.name}.png", folder / f"{image.stem}.png",
                  folder / image.name]
    candidates += [folder / f"{view_name}{suffix}" for suffix in images.IMAGE_SUFFIXES]
    return next((path for path in candidates if path.is_file()), None)


def missing_error(folder: Path, missing: Sequence[str], total: int, without: str = "give --masks none"
                  ) -> DataError:
    """The error for images without a mask; `without` says how the command goes on without masks."""
    shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
    return DataError(f"{folder} has no mask for {len(missing)} of the {total} images ({shown}); add "
                     f"{folder.name}/<image name>.png for each (white: keep, black: leave out), or {without}")


def load_masks(jobs: Sequence[MaskJob], invert: bool, workers: int | None = None) -> list[torch.Tensor]:
    """uint8 [H, W] keep weights (255 kept, 0 left out) of each job, decoded in parallel."""
    workers = workers or min(8, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcsplat-masks") as pool:
        return list(pool.map(lambda job: _load_one(job, invert), jobs))


def check_something_kept(keep: Sequence[torch.Tensor], jobs: Sequence[MaskJob], names: Sequence[str], where: str,
                         invert: bool) -> None:
    """Refuse masks that leave out every pixel of their image (as loaded): such a view has nothing to train on or
    to score, and when every view is one, a run would train on its regularisers alone and end as if it had worked."""
    empty = [i for i, mask in enumerate(keep) if not bool(mask.any())]
    if not empty:
        return
    if len(empty) == len(keep):
        fix = ("--invert-masks made them black: run without --invert-masks" if invert else
               "if yours are black where the image is to be kept, add --invert-masks")
        raise DataError(f"every one of the {len(keep)} masks from {where}{' (inverted)' if invert else ''} leaves out "
                        f"every pixel of its image, so nothing is left to train on; a mask keeps its white pixels "
                        f"and leaves out the black ones: {fix}")
    first = jobs[empty[0]]
    label = f"the alpha channel of {first.source}" if first.alpha else f"mask {first.source}"
    more = f" (and {len(empty) - 1} more: {', '.join(names[i] for i in empty[1:4])}" \
           f"{' ...' if len(empty) > 4 else ''})" if len(empty) > 1 else ""
    raise DataError(f"{label} leaves out every pixel of {names[empty[0]]}{more}, so nothing of that view is left to "
                    "train on or to score; give it a mask that keeps part of it (white: keep), or give --masks none")


def _load_one(job: MaskJob, invert: bool) -> torch.Tensor:
    keep = _read(job, invert)
    height, width = keep.shape
    expected_width, expected_height = job.file_size
    if abs(width / height - expected_width / expected_height) > ASPECT_TOLERANCE * expected_width / expected_height:
        raise DataError(f"mask {job.source} is {width}x{height} but its image is {expected_width}x{expected_height}; "
                        "a mask must have its image's shape")
    if (width, height) != tuple(job.file_size):
        keep = _resized(keep, job.file_size)
    if job.undistort is not None:
        keep = _undistorted(keep, job.undistort)
    if (keep.shape[1], keep.shape[0]) != tuple(job.size):
        keep = _resized(keep, job.size)
    return torch.from_numpy(np.ascontiguousarray(keep))


def _read(job: MaskJob, invert: bool) -> np.ndarray:
    """The keep weights of the file at its own size: uint8, 255 kept."""
    keep = read_keep(job.source, job.alpha)
    return 255 - keep if invert else keep


def read_keep(source: Path, alpha: bool = False) -> np.ndarray:
    """The keep weights [H, W] of a mask file (nonzero kept) or of an image's alpha channel: uint8, 255 kept; a
    file that is missing or does not decode whole is a one-line DataError naming it."""
    try:
        with Image.open(source) as im:
            if alpha:
                return np.array(im.convert("RGBA"))[:, :, 3]
            return np.where(np.asarray(im.convert("L")) > 0, 255, 0).astype(np.uint8)
    except FileNotFoundError:
        raise DataError(f"mask file is missing: {source}") from None
    except Exception as exc:
        raise DataError(f"cannot decode mask {source}: {images._reason(exc)}; replace the file") from None


def _resized(keep: np.ndarray, size: images.Size) -> np.ndarray:
    return np.clip(np.rint(images._area_resize(keep[:, :, None], size)[:, :, 0]), 0, 255).astype(np.uint8)


def _undistorted(keep: np.ndarray, job) -> np.ndarray:
    """The mask through the undistortion its image went through (data/undistort.py)."""
    import pycolmap

    rgb = np.ascontiguousarray(np.repeat(keep[:, :, None], 3, axis=2))
    bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(rgb),
                                         job.camera)
    return np.ascontiguousarray(bitmap.to_array()[:, :, 0])


def describe(masks: Sequence[torch.Tensor | None], source: str) -> str:
    """The line Scene.notes gets: how many views have a mask and what share of their pixels is left out."""
    present = [mask for mask in masks if mask is not None]
    left_out = sum(float((255 - mask.to(torch.float32)).sum()) for mask in present) / 255.0
    pixels = sum(mask.numel() for mask in present)
    share = 100 * left_out / max(pixels, 1)
    return f"{NOTE_PREFIX} {len(present)} of {len(masks)} images from {source}: {share:.1f}% of their pixels left out"
