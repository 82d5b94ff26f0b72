"""Lens distortion removed at load time: each distorted image becomes a pinhole image, once, cached outside the scene.

The new camera is COLMAP's choice (pycolmap.undistort_camera with its default options): the focal length is kept and
the image size changes so that the picture holds only valid pixels (no black borders for the loss to learn). The
undistorted images are written as PNG to a cache folder outside the user's scene, under a key made of the image's
bytes, the camera and the output size, so a changed image or model never meets a stale entry. Beside each entry lies
a hash of its own bytes: an entry that was damaged or replaced since it was made is made again, never served.
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from . import images
from ..errors import DataError
from ..io.hashed import content_hash, feed_file, hash_file, intact

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Models pycolmap undistorts to a pinhole camera (checked one by one; the last four are fisheye variants).
UNDISTORTABLE_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
                        "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "FOV")
CACHE_ENV = "MCSPLAT_CACHE"
CACHE_VERSION = "undistort-v1"  # bump when the output of this module changes for the same input
_ROUND_TRIP_TOLERANCE = 0.5  # pixels


def is_distorted(camera) -> bool:
    return camera.model.name not in PINHOLE_MODELS


def cache_root() -> Path:
    """$MCSPLAT_CACHE, else $XDG_CACHE_HOME/mcsplat, else ~/.cache/mcsplat: never inside a scene folder."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "mcsplat"


def pinhole_camera(camera, where: str):
    """The PINHOLE pycolmap camera that `camera`'s images become; DataError for what a pinhole cannot represent."""
    import pycolmap

    model = camera.model.name
    if model not in UNDISTORTABLE_MODELS:
        raise DataError(f"{where}: camera {camera.camera_id} uses the {model} model, which mcsplat cannot undistort "
                        f"(it handles {', '.join(PINHOLE_MODELS + UNDISTORTABLE_MODELS)}); undistort the images "
                        "with the tool that made them, or re-run SfM with an OPENCV camera (mcsplat process)")
    params = np.asarray(camera.params, dtype=np.float64)
    # A wrong parameter count crashes pycolmap's C++ code, so check before handing the camera over.
    if not camera.verify_params() or not np.isfinite(params).all() or camera.width < 2 or camera.height < 2:
        raise DataError(f"{where}: camera {camera.camera_id} ({model}) has invalid parameters {params.tolist()} "
                        f"for a {camera.width}x{camera.height} image; expected {camera.params_info}")
    _check_field_of_view(camera, where)
    return pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), camera)



def rescaled_camera(camera, size: images.Size):
    """A copy of a pycolmap camera for images of `size` (width, height); the camera itself when it has that size."""
    import pycolmap

    if (camera.width, camera.height) == tuple(size):
        return camera
    copy = pycolmap.Camera(model=camera.model.name, width=camera.width, height=camera.height,
                           params=np.asarray(camera.params, dtype=np.float64))
    copy.rescale(int(size[0]), int(size[1]))
    return copy

def _check_field_of_view(camera, where: str) -> None:
    """A pinhole camera sees less than 180 degrees: pixels on the image border must map to rays in front of it.

    pycolmap answers anyway for rays beyond 90 degrees from the axis (a wide fisheye), with a wrong camera; a pixel
    that does not survive the trip to a ray and back is how such a ray shows.
    """
    width, height = camera.width, camera.height
    t = np.linspace(0.0, 1.0, 33)
    zero, one = np.zeros_like(t), np.ones_like(t)
    border = np.concatenate([np.stack([t * width, zero], 1), np.stack([t * width, one * height], 1),
                             np.stack([zero, t * height], 1), np.stack([one * width, t * height], 1)])
    rays = np.asarray(camera.cam_from_img(border), dtype=np.float64)
    back = np.asarray(camera.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1)), dtype=np.float64)
    error = np.linalg.norm(back - border, axis=1)
    if not np.isfinite(error).all() or error.max() > _ROUND_TRIP_TOLERANCE:
        raise DataError(f"{where}: camera {camera.camera_id} ({camera.model.name}) sees 180 degrees or more across "
                        "the image, which no pinhole image can hold; crop the images to their central part (and "
                        "shift cx, cy) or use a narrower lens")


@dataclass(frozen=True)
class Job:
    """Undistort `source` (taken with `camera`) to `pinhole`, resized to `size` (width, height)."""

    source: Path
    camera: object  # pycolmap.Camera, distorted, at the size of the file
    pinhole: object  # pycolmap.Camera
    size: images.Size

    def key(self, background: Sequence[float]) -> str:
        digest = hashlib.blake2b(digest_size=20)
        for part in (CACHE_VERSION, self.camera.model.name, self.camera.width, self.camera.height,
                     np.asarray(self.camera.params, dtype=np.float64).tobytes().hex(), self.pinhole.width,
                     self.pinhole.height, np.asarray(self.pinhole.params, dtype=np.float64).tobytes().hex(),
                     self.size, tuple(background)):
            digest.update(repr(part).encode())
        feed_file(digest, self.source)  # the bytes, not the date: a replaced file is always seen
        return digest.hexdigest()


def undistort_to_cache(jobs: Sequence[Job], background: Sequence[float], workers: int | None = None,
                       progress: bool = True) -> list[Path]:
    """The cached undistorted PNG of each job, making the missing ones in parallel (pycolmap releases the GIL)."""
    from tqdm import tqdm

    folder = cache_root() / "undistorted"
    keys = [job.key(background) for job in jobs]
    paths = [folder / key[:2] / f"{key}.png" for key in keys]
    todo = [(job, path) for job, path in zip(jobs, paths) if not intact(path)]
    if not todo:
        return paths
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create the undistortion cache {folder}: {exc.strerror}; set {CACHE_ENV} to a "
                        "writable folder") from None
    bg = np.asarray(background, dtype=np.float32) * 255.0
    workers = workers or os.cpu_count() or 1
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mcsplat-undistort") as pool, \
            tqdm(total=len(todo), desc="undistorting", unit="image", disable=not progress or len(todo) < 2,
                 leave=False) as bar:
        futures = [pool.submit(_undistort_one, job, path, bg) for job, path in todo]
        try:
            for future in futures:
                future.result()
                bar.update(1)
        finally:
            for future in futures:
                future.cancel()
    return paths


def _undistort_one(job: Job, target: Path, background: np.ndarray) -> None:
    import pycolmap

    from ..io.atomic import atomic_path, atomic_write_text

    pixels = images._load_one(job.source, (job.camera.width, job.camera.height), background).numpy()
    bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(pixels),
                                         job.camera)
    out = np.ascontiguousarray(bitmap.to_array()[:, :, :3])
    if (out.shape[1], out.shape[0]) != (job.pinhole.width, job.pinhole.height):
        raise DataError(f"undistorting {job.source} gave a {out.shape[1]}x{out.shape[0]} image, expected "
                        f"{job.pinhole.width}x{job.pinhole.height}; please report this")
    if (job.pinhole.width, job.pinhole.height) != tuple(job.size):
        out = np.clip(np.rint(images._area_resize(out, job.size)), 0, 255).astype(np.uint8)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        Image.fromarray(out, "RGB").save(tmp, format="PNG", compress_level=1)
        content = content_hash(tmp)
    atomic_write_text(hash_file(target), content)

