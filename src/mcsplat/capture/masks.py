"""`mcsplat process --masks DIR`: the user's masks handed to SIFT, and carried into the scene it writes.

The masks are named as training masks are (data/attachments/masks.py: `<photo stem>.png`, `<photo name>.png` ...;
nonzero = keep, --invert-masks swaps). For SfM they are rewritten in COLMAP's convention (`<photo name>.png`, 0 = no features
there) into the work folder; a second copy, named exactly like the photos, goes through the same undistortion as the
photos (pycolmap.undistort_images), so that the scene gets a masks/ folder aligned with its undistorted images,
which `mcsplat train` then uses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from ..data.attachments import masks as training_masks
from ..errors import MCSplatError

SIFT_MASKS = "sift_masks"          # work/sift_masks/<photo name>.png: what pycolmap's mask_path reads
MASKS_AS_PHOTOS = "masks_as_photos"  # work/masks_as_photos/<photo name>: undistorted as the photos are
KEEP_LEVEL = 128                     # an undistorted (interpolated, maybe JPEG-compressed) mask is kept above this


def prepare(mask_dir: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]], invert: bool,
            work: Path) -> tuple[Path, Path]:
    """Write both copies of the masks of the photos `names` (in `folder`, of `sizes`); returns their folders."""
    if not mask_dir.is_dir():
        raise MCSplatError(f"--masks {mask_dir}: no such folder; give the folder that holds one mask PNG per photo")
    files = [training_masks.mask_file(mask_dir, str(Path(name).with_suffix("")), folder / name) for name in names]
    missing = [name for name, file in zip(names, files) if file is None]
    if missing:
        # process has no --masks none (the photos have no masks/ it would find by itself): leaving it out is the way
        raise training_masks.missing_error(mask_dir, missing, len(names), without="leave --masks out")
    sift, as_photos = work / SIFT_MASKS, work / MASKS_AS_PHOTOS
    for name, file, size in zip(names, files, sizes):
        keep = training_masks.read_keep(file) > 0  # a file that does not decode whole: one line naming it
        if keep.shape[::-1] != tuple(size):
            raise MCSplatError(f"mask {file} is {keep.shape[1]}x{keep.shape[0]} but its photo {name} is "
                               f"{size[0]}x{size[1]}; a mask must have its photo's size")
        pixels = np.where(keep != invert, 255, 0).astype(np.uint8)
        for target in (sift / f"{name}.png", as_photos / name):
            target.parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(pixels).save(target, format="PNG")  # PNG whatever the name says: lossless
    return sift, as_photos


def write_scene_masks(undistorted_images: Path, scene_masks: Path) -> int:
    """The undistorted masks (named like the photos) as the scene's masks/<photo path without suffix>.png; returns
    how many were written."""
    count = 0
    for file in sorted(p for p in undistorted_images.rglob("*") if p.is_file()):
        with Image.open(file) as im:
            keep = np.asarray(im.convert("L")) >= KEEP_LEVEL
        target = scene_masks / file.relative_to(undistorted_images).with_suffix(".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.where(keep, 255, 0).astype(np.uint8)).save(target)
        count += 1
    return count
