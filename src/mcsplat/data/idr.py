"""IDR / NeuS / MonoSDF scenes (DTU and BlendedMVS in that layout): cameras.npz and one image per camera.

cameras.npz holds, for camera i, `world_mat_i` = K [R | t] (a 4x4 whose top 3x4 is the projection, OpenCV axes) and
optionally `scale_mat_i`, which maps the unit sphere onto the object. The cameras are used in those normalised
coordinates, P = world_mat @ scale_mat, as IDR, NeuS and MonoSDF do: the object fills the unit sphere.

Images: `image/*.png` (IDR, NeuS) or `*_rgb.png` next to cameras.npz (MonoSDF), in sorted order, image k for
camera k. MonoSDF's DTU images are 384x384 crops of the 1600x1200 captures whose intrinsics cameras.npz keeps (its
`center_crop_for_dtu`: the centred 1200x1200 square, resized); that layout is recognised and K follows the crop.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import scipy.linalg

from . import images
from .assemble import Frame, assemble
from .poses import scale_intrinsics
from .scene import Background, Scene
from ..errors import DataError

CAMERAS_FILE = "cameras.npz"
DTU_CAPTURE = (1600, 1200)  # the DTU camera's image size (width, height), MonoSDF's crop source
CENTRAL = 0.15              # a principal point within 15% of the image centre is taken to belong to that image


def is_idr(root: Path) -> bool:
    return (root / CAMERAS_FILE).is_file()


def image_paths(root: Path) -> list[Path]:
    folder = root / "image"
    if folder.is_dir():
        found = [p for p in folder.iterdir() if p.suffix in images.IMAGE_SUFFIXES and not p.name.startswith(".")]
    else:
        found = [p for p in root.iterdir() if p.stem.endswith("_rgb") and p.suffix in images.IMAGE_SUFFIXES]
    return sorted(found, key=lambda p: p.name)


def read_projections(path: Path, count: int) -> list[tuple[np.ndarray, float]]:
    """The count 3x4 projections world_mat_i @ scale_mat_i (scale_mat_i: identity where absent), each with the
    scene units per unit of the capture (1 / scale_mat_i's scale): a length measured in the capture is that times
    smaller in the unit sphere."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.asarray(data[key], dtype=np.float64) for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        reason = " ".join(str(exc).split())[:200] or type(exc).__name__
        raise DataError(f"cannot read {path}: {reason}; it must be a numpy .npz with world_mat_0, world_mat_1, "
                        "...") from None
    projections = []
    for i in range(count):
        world = arrays.get(f"world_mat_{i}")
        if world is None:
            raise DataError(f"{path} has no world_mat_{i}, but there are {count} images; cameras.npz needs one "
                            "world_mat_i per image (sorted by name)")
        scale = arrays.get(f"scale_mat_{i}", np.eye(4))
        if world.shape != (4, 4) or scale.shape != (4, 4) or not (np.isfinite(world).all() and np.isfinite(scale).all()):
            raise DataError(f"{path}: world_mat_{i} and scale_mat_{i} must be finite 4x4 matrices, got "
                            f"{list(world.shape)} and {list(scale.shape)}")
        volume = abs(np.linalg.det(scale[:3, :3]))  # a singular one is refused by decompose
        units = 1.0 / volume ** (1.0 / 3.0) if volume > 0 else 1.0
        projections.append(((world @ scale)[:3, :4], units))
    return projections


def decompose(projection: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(K with K[2, 2] = 1, world-to-camera 4x4) of P = s K [R | t]."""
    upper, rotation = scipy.linalg.rq(projection[:, :3])
    signs = np.diag(np.sign(np.diag(upper)))
    if (np.diag(signs) == 0).any():
        raise DataError(f"{where}: the projection's 3x3 part is singular; it is not a camera")
    upper, rotation = upper @ signs, signs @ rotation
    translation = np.linalg.solve(upper, projection[:, 3])
    if np.linalg.det(rotation) < 0:  # P and -P project alike; keep the proper rotation
        rotation, translation = -rotation, -translation
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, translation
    return upper / upper[2, 2], w2c


def _central(K: np.ndarray, size: tuple[int, int]) -> bool:
    return abs(K[0, 2] - size[0] / 2) <= CENTRAL * size[0] and abs(K[1, 2] - size[1] / 2) <= CENTRAL * size[1]


def intrinsics_for(K: np.ndarray, image_size: tuple[int, int], where: str) -> tuple[np.ndarray, str | None]:
    """K for images of image_size: as given when its principal point sits in them; MonoSDF's DTU crop when the
    images are square and K is the 1600x1200 DTU camera's. Returns (K, a note or None)."""
    if _central(K, image_size):
        return K, None
    width, height = image_size
    if width == height and _central(K, DTU_CAPTURE):
        side = min(DTU_CAPTURE)
        cropped = K.copy()
        cropped[0, 2] -= (DTU_CAPTURE[0] - side) / 2
        return scale_intrinsics(cropped, (side, side), image_size), (
            f"intrinsics of the {DTU_CAPTURE[0]}x{DTU_CAPTURE[1]} DTU camera, centre-cropped to {side}x{side} and "
            f"scaled to {width}x{height} (MonoSDF's layout)")
    raise DataError(f"{where}: its principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) does not fit the "
                    f"{width}x{height} images (nor MonoSDF's crop of the 1600x1200 DTU camera); the images must be "
                    "the ones the cameras were calibrated for")


def load_idr(root: Path, downscale: int, background: Background | None, test_every: int) -> Scene:
    paths = image_paths(root)
    cameras_file = root / CAMERAS_FILE
    if not paths:
        raise DataError(f"{root} has {CAMERAS_FILE} but no images: expected image/*.png or *_rgb.png beside it")
    sizes = images.probe_sizes(paths)
    for path, size in zip(paths, sizes):
        if size != sizes[0]:
            raise DataError(f"image {path} is {size[0]}x{size[1]} but {paths[0]} is {sizes[0][0]}x{sizes[0][1]}; all "
                            "images of the scene must have one size")
    target = images.downscaled_size(*sizes[0], downscale)
    frames, notes = [], []
    for index, (path, (projection, units)) in enumerate(zip(paths, read_projections(cameras_file, len(paths)))):
        where = f"{cameras_file} camera {index}"
        K, w2c = decompose(projection, where)
        K, note = intrinsics_for(K, sizes[0], where)
        if note and note not in notes:
            notes.append(note)
        frames.append(Frame(path, path.stem, scale_intrinsics(K, sizes[0], target), w2c, target, units=units))
    if target != sizes[0]:
        notes.append(f"images resized to {target[0]}x{target[1]}")
    notes.append("no SfM points (the object fills the unit sphere: random init)")
    return assemble(frames, kind="idr", root=root, background=background, test_every=test_every, notes=notes)
