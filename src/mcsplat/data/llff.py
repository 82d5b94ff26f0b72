"""LLFF scenes: poses_bounds.npy (N x 17) with images*/ folders, and SfM points from sparse/0/points3D if present.

Each row of poses_bounds.npy is a 3x5 matrix flattened row-major, then the near/far bounds. Its first four columns
are the camera-to-world pose with rotation columns [down, right, backwards] (in COLMAP's world frame), the fifth is
(height, width, focal) of the full-resolution images. Rows follow the sorted image file names.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import colmap_files, images
from .assemble import Frame, Points, assemble
from .poses import intrinsic_matrix, llff_to_opencv_w2c
from .scene import Background, Scene
from ..errors import DataError

POSES_FILE = "poses_bounds.npy"


def is_llff(root: Path) -> bool:
    return (root / POSES_FILE).is_file()


def read_poses_bounds(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as exc:  # ValueError, OSError, EOFError, UnpicklingError ...
        reason = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise DataError(f"cannot read {path}: {reason}; it must be a float array of shape (N, 17) saved with "
                        "numpy.save") from None
    if array.ndim != 2 or array.shape[1] != 17 or array.shape[0] == 0 or not np.issubdtype(array.dtype, np.number):
        raise DataError(f"{path} holds an array of shape {list(array.shape)} ({array.dtype}); LLFF poses_bounds.npy "
                        "must be (N, 17): 3x5 [R|t|hwf] per image plus near/far")
    return array.astype(np.float64)


def _points(root: Path) -> Points | None:
    for folder in (root / "sparse" / "0", root / "sparse"):
        if (folder / "points3D.bin").is_file():
            return Points(*colmap_files.read_points3d_bin(folder / "points3D.bin"), str(folder / "points3D.bin"))
        if (folder / "points3D.txt").is_file():
            return Points(*colmap_files.read_points3d_text(folder / "points3D.txt"), str(folder / "points3D.txt"))
    return None


def load_llff(root: Path, downscale: int, background: Background | None, test_every: int) -> Scene:
    poses_file = root / POSES_FILE
    array = read_poses_bounds(poses_file)
    poses = array[:, :15].reshape(-1, 3, 5)
    world_to_camera = [llff_to_opencv_w2c(p[:, :4], f"{poses_file} row {i}") for i, p in enumerate(poses)]
    hwf = poses[:, :, 4]
    bad = np.flatnonzero(~(np.isfinite(hwf).all(axis=1) & (hwf > 0).all(axis=1)))
    if bad.size:
        raise DataError(f"{poses_file} row {bad[0]}: height, width, focal {hwf[bad[0]].tolist()} must be positive "
                        "numbers")

    image_dir, factor = images.choose_image_dir(root, downscale)
    paths = sorted((p for p in image_dir.iterdir() if p.suffix in images.IMAGE_SUFFIXES and not p.name.startswith(".")),
                   key=lambda p: p.name)
    if len(paths) != len(poses):
        raise DataError(f"{image_dir} has {len(paths)} images but {poses_file} has {len(poses)} poses; there must be "
                        "one image per pose row (rows follow the sorted file names)")
    sizes = images.probe_sizes(paths)
    for path, size in zip(paths, sizes):
        if size != sizes[0]:
            raise DataError(f"image {path} is {size[0]}x{size[1]} but {paths[0]} is {sizes[0][0]}x{sizes[0][1]}; all "
                            "images of an LLFF scene must have one size")
    width, height = sizes[0]
    full_height, full_width = hwf[0, 0], hwf[0, 1]
    if abs(width / height - full_width / full_height) > 0.01 * full_width / full_height:
        raise DataError(f"images in {image_dir} are {width}x{height} but {poses_file} says the images are "
                        f"{full_width:g}x{full_height:g} (a different aspect ratio); use the matching images")

    target = images.downscaled_size(width, height, downscale / factor) if downscale > factor else (width, height)
    frames = []
    for path, row_hwf, w2c in zip(paths, hwf, world_to_camera):
        focal = row_hwf[2] * target[1] / row_hwf[0]
        frames.append(Frame(path, path.stem, intrinsic_matrix(focal, focal, target[0] / 2, target[1] / 2), w2c,
                            target))

    notes = [f"images from {image_dir.name}/" + (f", resized to {target[0]}x{target[1]}" if target != (width, height)
                                                  else "")]
    if downscale < factor:
        asked = "images/" if downscale == 1 else f"images_{downscale}/ or images/"
        notes.append(f"no {asked} folder; using the smaller {image_dir.name}/ as it is")
    points = _points(root)
    if points is None:
        notes.append("no sparse/0/points3D.bin: no SfM points")
    return assemble(frames, kind="llff", root=root, background=background, test_every=test_every, points=points,
                    notes=notes)
