"""Depth maps: how far the surface is behind each pixel of a photo, as a sensor, a renderer or another method saw it.

Found beside the photo (`<photo stem>_depth.npy`, `_depth.png`, or Blender's numbered `_depth_0001.png`, as
NeRF-synthetic's test views have them) or in the scene's depths/ folder (or the folder DepthOptions names) as
`<view name>.npy` / `.png`, `<image stem>.npy` / `.png`. A view without one has none: depth is often measured for some
views only (NeRF-synthetic renders it for its test views alone).

Decoded to float32 [H, W]: the distance along the camera's optical axis (z, as render()'s depth is), in the scene's
units (the capture's times the loader's scale: IDR's scale_mat shrinks the object into the unit sphere); 0 where the
file has no depth (0, NaN or inf). A `.npy` holds floats in the capture's units; a 16-bit PNG holds steps of
`depth_png_step` (0.001: millimetres of a capture in metres); NeRF-synthetic's 8-bit PNGs hold 8 (1 - R/255) along the
ray (shared/data/nerf_synthetic_lego_400/SOURCE.md), R = 0 where there is no object.

A depth is a value, not a weight: it follows its image by NEAREST (resampling.py), never averaged across an edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np
import torch
from PIL import Image

from .. import images, undistort
from .kind import Found, Kind
from .resampling import NEAREST
from ...compute.device import upload
from ...errors import DataError
from ...option_checks import refuse_non_finite

DEPTH_FOLDER = "depths"
BESIDE_PHOTO = ("{stem}_depth.npy", "{stem}_depth.png", "{stem}_depth_0001.png")
IN_FOLDER = ("{view}.npy", "{view}.png", "{stem}.npy", "{stem}.png")
ENCODINGS = ("metric", "nerf-synthetic")
MEASURES = ("z", "ray")
REAL_KINDS = "iuf"  # numpy dtype kinds a .npy depth map may have: signed, unsigned integers, floats
NERF_SYNTHETIC_FAR = 8.0  # R = 0 would be this far; the dataset's renders put 0 where there is no object instead


@dataclass(frozen=True)
class DepthOptions:
    """Depth maps beside the photos (--depths), and how their numbers read."""

    depths: str = field(default="auto", metadata={"folder_unless": ("auto", "none")})
    """Depth maps loaded onto the views, for --depth-loss: 'none', 'auto' (beside each photo as <photo
    stem>_depth.npy / .png, or the scene's depths/ folder) or a folder of <image name>.npy / .png. A view without one
    has none."""
    depth_encoding: Literal["metric", "nerf-synthetic"] = "metric"
    """metric: .npy floats, or 16-bit PNG steps of --depth-png-step, in the capture's units; nerf-synthetic: its
    8-bit renders (8 (1 - R/255) along the ray, R = 0: no object)."""
    depth_measure: Literal["z", "ray"] = "z"
    """What a metric depth map measures: z (along the optical axis) or ray (from the camera along the pixel's ray)."""
    depth_png_step: float = 0.001
    """A 16-bit PNG depth map's step in the capture's units (0.001: millimetres of a capture in metres)."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not self.depths.strip():
            raise DataError(f"--depths {self.depths!r} names no folder: give 'auto', 'none' or the folder that holds "
                            "one depth map per image")
        if self.depth_encoding not in ENCODINGS:
            raise DataError(f"--depth-encoding {self.depth_encoding!r} is not known: give one of "
                            f"{', '.join(ENCODINGS)}")
        if self.depth_measure not in MEASURES:
            raise DataError(f"--depth-measure {self.depth_measure!r} is not known: give 'z' (along the optical axis) "
                            "or 'ray' (along the pixel's ray)")
        step = self.depth_png_step
        if not (isinstance(step, (int, float)) and math.isfinite(step) and step > 0):
            raise DataError(f"--depth-png-step {step!r} must be a positive number (the capture's units per step of a "
                            "16-bit PNG: 0.001 for millimetres of a capture in metres)")

    def per_view_input(self) -> DepthOptions:
        """What a run's feature seam (features.py) loads beside the photos for it: these options."""
        return self

    @property
    def along_ray(self) -> bool:
        return self.depth_encoding == "nerf-synthetic" or self.depth_measure == "ray"


class DepthKind(Kind):
    name = "depth"
    label = "depth map"
    options = DepthOptions
    resampling = NEAREST

    def find(self, options: DepthOptions, scene: Any) -> Found | None:
        views = scene.train + scene.test
        if options.depths == "none":
            return None
        if options.depths == "auto":
            folder = scene.root / DEPTH_FOLDER
            folder = folder if folder.is_dir() else None
            beside = [_beside(view.source.photo) for view in views]
            files = [file or (folder and _in_folder(folder, view)) for file, view in zip(beside, views)]
            if not any(files):
                return None
            places = (["beside the photos"] if any(beside) else []) + \
                ([str(folder)] if any(file and not near for file, near in zip(files, beside)) else [])
            return Found(files, " and ".join(places))
        folder = Path(options.depths).expanduser()
        if not folder.is_dir():
            raise DataError(f"--depths {options.depths}: no such folder; give the folder that holds one depth map "
                            "per image, 'auto' (beside the photos, or the scene's depths/) or 'none'")
        files = [_in_folder(folder, view) for view in views]
        if not any(files):
            raise DataError(f"{folder} holds no depth map for any of the {len(views)} images; name each "
                            f"<view name>.npy or .png (for the first: {views[0].name}.npy)")
        return Found(files, str(folder))

    def decode(self, file: Path, view: Any, options: DepthOptions) -> np.ndarray:
        depth = _read(file, options)
        with np.errstate(invalid="ignore"):
            depth[~np.isfinite(depth)] = 0.0
            if (depth < 0).any():
                raise DataError(f"depth map {file} holds negative depths (down to {depth.min():.4g}); a depth is a "
                                "distance in front of the camera: write 0 (or NaN) where there is none")
        if options.along_ray:
            depth /= _ray_lengths(view, (depth.shape[1], depth.shape[0]))
        return _as_float32(depth * view.source.units, file)

    def as_float(self, values: torch.Tensor, device: torch.device | str) -> torch.Tensor:
        return upload(values, device)[:, :, None]

    def note(self, values: Sequence[torch.Tensor | None], found: Found, options: DepthOptions) -> str:
        present = [depth for depth in values if depth is not None]
        known = torch.cat([depth[depth > 0] for depth in present])
        pixels = sum(depth.numel() for depth in present)
        span = f"{float(known.min()):.3g} to {float(known.max()):.3g} scene units" if known.numel() else "all empty"
        return (f"depth maps for {len(present)} of {len(values)} images from {found.where} ({options.depth_encoding}): "
                f"{span}, {100 * (1 - known.numel() / max(pixels, 1)):.1f}% of their pixels without one")


def _as_float32(depth: np.ndarray, file: Path) -> np.ndarray:
    """The depths as float32, which a view keeps; a depth beyond its range would become inf, a target no render
    reaches, where the file meant a number (NaN and inf were made 0, no depth, before)."""
    with np.errstate(over="ignore"):
        single = depth.astype(np.float32)
    if not np.isfinite(single).all():
        raise DataError(f"depth map {file} holds depths up to {depth.max():.4g} scene units, beyond float32's range "
                        f"({np.finfo(np.float32).max:.3g}); save the depths in the capture's units, with 0, NaN or inf "
                        "where there is none")
    return single


def _beside(photo: Path) -> Path | None:
    candidates = [photo.with_name(pattern.format(stem=photo.stem)) for pattern in BESIDE_PHOTO]
    return next((path for path in candidates if path.is_file()), None)


def _in_folder(folder: Path, view: Any) -> Path | None:
    candidates = [folder / pattern.format(view=view.name, stem=view.source.photo.stem) for pattern in IN_FOLDER]
    return next((path for path in candidates if path.is_file()), None)


def _read(file: Path, options: DepthOptions) -> np.ndarray:
    """The file's numbers as float64 [H, W] in the capture's units, as the encoding says (before ray to z)."""
    if file.suffix == ".npy":
        if options.depth_encoding != "metric":
            raise DataError(f"depth map {file} is a .npy, but the {options.depth_encoding} encoding is a PNG's; give "
                            "encoding 'metric' for .npy files")
        try:
            array = np.load(file, allow_pickle=False)
        except Exception as exc:  # ValueError, OSError, EOFError ...
            raise DataError(f"cannot read depth map {file}: {images._reason(exc)}; it must be a float array saved "
                            "with numpy.save") from None
        if array.ndim == 3 and array.shape[2] == 1:
            array = array[:, :, 0]
        # Real numbers only: a complex array would lose its imaginary part with a mere warning, a timedelta read
        # as a count; numpy calls both numbers.
        if array.ndim != 2 or array.dtype.kind not in REAL_KINDS or min(array.shape) == 0:
            raise DataError(f"depth map {file} holds an array of shape {list(array.shape)} ({array.dtype}); it must "
                            "be [height, width] real numbers (integers or floats), one depth per pixel")
        return array.astype(np.float64)
    try:
        with Image.open(file) as im:
            im.load()
            mode, array = im.mode, np.asarray(im)
    except FileNotFoundError:
        raise DataError(f"depth map file is missing: {file}") from None
    except Exception as exc:
        raise DataError(f"cannot decode depth map {file}: {images._reason(exc)}; replace the file") from None
    sixteen_bit = mode.startswith("I;16") or mode == "I"
    if options.depth_encoding == "nerf-synthetic":
        if sixteen_bit or array.dtype != np.uint8:
            raise DataError(f"depth map {file} is a {mode} PNG, but NeRF-synthetic's are 8-bit; give encoding "
                            "'metric' for 16-bit PNGs")
        red = (array if array.ndim == 2 else array[:, :, 0]).astype(np.float64)
        return np.where(red > 0, NERF_SYNTHETIC_FAR * (1.0 - red / 255.0), 0.0)
    if not sixteen_bit:
        raise DataError(f"depth map {file} is an 8-bit {mode} PNG, whose 256 steps cannot hold a depth; save it as "
                        "a 16-bit PNG or a .npy, or give encoding 'nerf-synthetic' for NeRF-synthetic's renders")
    return array.astype(np.float64) * options.depth_png_step


def _ray_lengths(view: Any, size: images.Size) -> np.ndarray:
    """[H, W] |(x, y, 1)| of each pixel's ray at `size`, with the camera that took the file (the distorted one for
    a view that was undistorted): a distance along the ray over it is the distance along the axis."""
    width, height = size
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    job = view.source.undistort
    if job is not None:
        camera = undistort.rescaled_camera(job.camera, size)
        rays = np.asarray(camera.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1)), dtype=np.float64)
        x, y = rays[:, 0].reshape(height, width), rays[:, 1].reshape(height, width)
    else:
        K = view.camera.scaled(width, height).K.double().numpy()
        x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return np.sqrt(x * x + y * y + 1.0)


KIND = DepthKind()
