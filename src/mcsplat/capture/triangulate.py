"""Points from known poses: SIFT features and matches of a scene's training views, triangulated with the scene's own
cameras held fixed (pycolmap's triangulate_points, COLMAP's point_triangulator). This is what a scene that has poses
but no points (instant-ngp / nerfstudio transforms.json, LLFF without sparse/, IDR) starts from.

The result is cached outside the scene folder, under a key made of the views' image files, sizes and cameras, so a
second run on the same scene starts at once and a changed image or pose never meets a stale entry.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from mcsplat.capture.sfm import extract_features, match_features, uses_gpu
from mcsplat.data import View
from mcsplat.data.undistort import cache_root
from mcsplat.errors import MCSplatError
from mcsplat.io.atomic import atomic_path, atomic_write_text

CACHE_VERSION = "points-v1"  # bump when the output changes for the same input
MAX_VIEWS = 100              # more views add little to an initialisation and cost pairs squared in matching
SIFT_MAX_SIZE = 1600         # as `mcsplat process`
MAX_FEATURES = 4096          # half COLMAP's default: matching costs features squared, and a start needs few points
MIN_POINTS = 100             # fewer is a failed triangulation


@dataclass
class Triangulated:
    xyz: np.ndarray  # [P, 3] float64
    rgb: np.ndarray  # [P, 3] uint8
    views: int       # views used
    seconds: float   # how long the triangulation took (when it was made)
    cached: bool     # read from the cache rather than made now
    reprojection_error: float  # mean, in pixels


def triangulated_points(views: Sequence[View], threads: int | None = None, progress: bool = True) -> Triangulated:
    """The points of `views` (every one of them, or MAX_VIEWS spread over them), from the cache when it has them.
    MCSplatError when too few points come out (too little texture or overlap)."""
    chosen = _spread(list(views), MAX_VIEWS)
    folder = cache_root() / CACHE_VERSION / _key(chosen)
    found = _read(folder)
    if found is not None:
        return found
    made = _triangulate(chosen, threads or os.cpu_count() or 1, progress)
    _write(folder, made)
    return made


def _spread(views: list[View], count: int) -> list[View]:
    if len(views) <= count:
        return views
    return [views[round(i * (len(views) - 1) / (count - 1))] for i in range(count)]


def _key(views: Sequence[View]) -> str:
    digest = hashlib.sha256(CACHE_VERSION.encode())
    for view in views:
        camera = view.camera
        digest.update(f"{view.name}|{camera.width}x{camera.height}|".encode())
        digest.update(camera.K.double().numpy().tobytes() + camera.world_to_camera.double().numpy().tobytes())
        source = view.image_file
        digest.update(source.read_bytes() if source is not None else view.image.numpy().tobytes())
    return digest.hexdigest()


def _read(folder: Path) -> Triangulated | None:
    try:
        with np.load(folder / "points.npz", allow_pickle=False) as data:
            xyz, rgb = data["xyz"], data["rgb"]
        facts = json.loads((folder / "facts.json").read_text())
    except (OSError, ValueError, KeyError):
        return None
    return Triangulated(xyz, rgb, facts["views"], facts["seconds"], True, facts["reprojection_error"])


def _write(folder: Path, made: Triangulated) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "points.npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, xyz=made.xyz, rgb=made.rgb)
    atomic_write_text(folder / "facts.json", json.dumps({"views": made.views, "seconds": round(made.seconds, 1),
                                                         "reprojection_error": made.reprojection_error}))


def _triangulate(views: list[View], threads: int, progress: bool) -> Triangulated:
    import pycolmap

    start = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="mcsplat-triangulate-"))
    try:
        images = work / "images"
        images.mkdir()
        names = [f"{i:05d}.png" for i in range(len(views))]
        for name, view in zip(names, views):
            Image.fromarray(view.image.numpy()).save(images / name)
        database = work / "database.db"
        gpu = uses_gpu(True)
        with _quiet_colmap():
            extract_features(database, images, [names], camera_model="PINHOLE", per_image=True,
                             max_size=SIFT_MAX_SIZE, threads=threads, gpu=gpu, progress=progress,
                             max_features=MAX_FEATURES)
            match_features(database, "exhaustive", overlap=0, threads=threads, gpu=gpu, progress=progress)
            known = _known_poses(database, dict(zip(names, views)))
            options = pycolmap.IncrementalPipelineOptions()
            options.num_threads = threads
            (work / "model").mkdir()
            model = pycolmap.triangulate_points(known, database, images, work / "model", options=options)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    points = list(model.points3D.values())
    if len(points) < MIN_POINTS:
        raise MCSplatError(f"triangulation from the known poses found only {len(points)} points in {len(views)} "
                           "views (too little texture or overlap)")
    xyz = np.array([p.xyz for p in points], dtype=np.float64)
    rgb = np.array([p.color for p in points], dtype=np.uint8)
    return Triangulated(xyz, rgb, len(views), time.perf_counter() - start, False,
                        float(model.compute_mean_reprojection_error()))


@contextlib.contextmanager
def _quiet_colmap():
    """COLMAP's INFO lines (one per image and stage) would bury the training's console: warnings and errors only."""
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def _known_poses(database: Path, views_by_name: dict[str, View]):
    """A reconstruction holding the views' cameras and poses under the database's image and camera ids."""
    import pycolmap

    known = pycolmap.Reconstruction()
    db = pycolmap.Database.open(str(database))
    try:
        for image in db.read_all_images():
            view = views_by_name[image.name]
            K = view.camera.K.double().numpy()
            known.add_camera_with_trivial_rig(pycolmap.Camera(
                model="PINHOLE", width=view.camera.width, height=view.camera.height,
                params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=image.camera_id))
            w2c = view.camera.world_to_camera.double().numpy()
            known.add_image_with_trivial_frame(
                pycolmap.Image(name=image.name, camera_id=image.camera_id, image_id=image.image_id),
                pycolmap.Rigid3d(w2c[:3, :4]))
    finally:
        db.close()
    return known
