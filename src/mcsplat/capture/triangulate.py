"""Points from known poses: SIFT features and matches of a scene's training views, triangulated with the scene's own
cameras held fixed (pycolmap's triangulate_points, COLMAP's point_triangulator). This is what a scene that has poses
but no points (instant-ngp / nerfstudio transforms.json, LLFF without sparse/, IDR) starts from.

The result is cached outside the scene folder, under a key made of the views' image files, sizes and cameras, so a
second run on the same scene starts at once and a changed image or pose never meets a stale entry. Each file of an
entry carries a hash of its bytes (io/hashed.py, as the undistortion cache's), and an entry is served only when its
points are what a fresh triangulation gives (enough of them, finite, inside the views' frustums): any other entry is
made again, saying so. A cache that cannot be written costs the next run the triangulation, not this one.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from PIL import Image

from .child import terminate_as_interrupt
from .sfm import extract_features, match_features, uses_gpu
from ..data import View
from ..data.undistort import CACHE_ENV, cache_root
from ..errors import MCSplatError
from ..io.hashed import NotARegularFile, read_intact, write_hashed

CACHE_VERSION = "points-v2"  # bump when the output (or the entry's files) change for the same input
MAX_VIEWS = 100              # more views add little to an initialisation and cost pairs squared in matching
SIFT_MAX_SIZE = 1600         # as `mcsplat process`
MAX_FEATURES = 4096          # half COLMAP's default: matching costs features squared, and a start needs few points
MIN_POINTS = 100             # fewer is a failed triangulation
IN_VIEW_SHARE = 0.99         # of the points, in some view's frustum: a fresh triangulation's all are (seen twice)
VIEW_MARGIN = 0.05           # of the image's size, around it: a point's reprojection error puts it a little outside
FAR = 100                    # cameras' spreads from their centre: beyond ~80, even the farthest two cameras see a
                             # point under less than the 1.5 degrees COLMAP's triangulation asks for


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
    found = cached_points(folder, chosen)
    if found is not None:
        return found
    import pycolmap  # noqa: F401  (before our handlers: importing it installs glog's, which dumps a stack on SIGTERM)

    with terminate_as_interrupt():  # kill or a closed terminal stop it as Ctrl-C does, its temporary folder removed
        made = _triangulate(chosen, threads or os.cpu_count() or 1, progress)
    store_points(folder, made)
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


class _Damaged(Exception):
    """Why a cache entry cannot be served."""


def cached_points(folder: Path, views: Sequence[View]) -> Triangulated | None:
    """The points of the cache entry `folder` (made from `views`), or None when there is none. A damaged entry is
    None too, with a warning that names it: the caller makes it again."""
    if not os.path.lexists(folder):
        return None
    try:
        return _read(folder, views)
    except _Damaged as why:
        warnings.warn(f"the points cache entry {folder} is damaged ({why}); triangulating again", stacklevel=3)
        return None


def _read(folder: Path, views: Sequence[View]) -> Triangulated:
    if not folder.is_dir():
        raise _Damaged("it is not a folder")
    try:
        points, facts = read_intact(folder / "points.npz"), read_intact(folder / "facts.json")
    except NotARegularFile as error:
        raise _Damaged(f"{Path(error.filename).name} is not a regular file") from None
    except FileNotFoundError as error:
        raise _Damaged(f"it has no {Path(error.filename).name}") from None
    except (OSError, ValueError) as error:
        raise _Damaged(str(error)) from None
    try:
        with np.load(io.BytesIO(points), allow_pickle=False) as data:
            xyz, rgb = data["xyz"], data["rgb"]
        facts = json.loads(facts)
    except Exception as error:  # whatever the bytes hold: np.load and json raise many kinds
        raise _Damaged(f"unreadable: {type(error).__name__}") from None
    views_used, seconds, error = _facts_of(facts)
    if views_used != len(views):
        raise _Damaged(f"its facts.json counts {views_used} views, not {len(views)}")
    problem = implausible_points(xyz, rgb, views)
    if problem is not None:
        raise _Damaged(problem)
    return Triangulated(xyz.astype(np.float64), rgb, views_used, seconds, True, error)


def _facts_of(facts) -> tuple[int, float, float]:
    """(views, seconds, mean reprojection error) of facts.json, checked."""
    if not isinstance(facts, dict):
        raise _Damaged("its facts.json is not an object")
    values = [facts.get(name) for name in ("views", "seconds", "reprojection_error")]
    views, seconds, error = values
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
                  for v in values)
    if not numbers or not isinstance(views, int):
        raise _Damaged("its facts.json lacks views, seconds or reprojection_error as numbers")
    return views, float(seconds), float(error)


def implausible_points(xyz: np.ndarray, rgb: np.ndarray, views: Sequence[View]) -> str | None:
    """What makes `xyz`, `rgb` unlike a triangulation from `views` (too few, not finite, outside every view), or
    None."""
    if xyz.ndim != 2 or xyz.shape[1:] != (3,) or rgb.shape != xyz.shape:
        return f"points of shape {xyz.shape} and colours of shape {rgb.shape}, not [P, 3] both"
    if xyz.dtype.kind != "f" or rgb.dtype != np.uint8:  # each named alone: a wrong type is no wrong shape
        wrong = ([f"points of {xyz.dtype}, not floats"] if xyz.dtype.kind != "f" else []) + \
            ([f"colours of {rgb.dtype}, not uint8 (0-255)"] if rgb.dtype != np.uint8 else [])
        return " and ".join(wrong)
    if len(xyz) < MIN_POINTS:
        return f"{len(xyz)} points, fewer than the {MIN_POINTS} of a triangulation"
    finite = np.isfinite(xyz).all(axis=1)
    if not finite.all():
        return f"{int((~finite).sum())} of its {len(xyz)} points are not finite"
    inside = _in_some_view(xyz, views)
    if inside.mean() < IN_VIEW_SHARE:
        return f"{int((~inside).sum())} of its {len(xyz)} points lie outside every camera's view"
    return None


def _in_some_view(xyz: np.ndarray, views: Sequence[View]) -> np.ndarray:
    """[P] bool: whether each point is in some view's frustum: in front of its camera, no further than FAR spreads of
    the cameras, and projecting into its image (VIEW_MARGIN around it)."""
    centres = np.stack([np.linalg.inv(view.camera.world_to_camera.double().numpy())[:3, 3] for view in views])
    middle = centres.mean(axis=0)
    spread = max(float(np.linalg.norm(centres - middle, axis=1).max()), 1e-9)
    inside = np.zeros(len(xyz), dtype=bool)
    for view in views:
        camera = view.camera
        w2c, K = camera.world_to_camera.double().numpy(), camera.K.double().numpy()
        local = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        depth = local[:, 2]
        uv = (local @ K.T)[:, :2] / np.where(depth > 0, depth, 1.0)[:, None]
        margin = VIEW_MARGIN * np.array([camera.width, camera.height])
        inside |= (depth > 0) & (uv >= -margin).all(axis=1) & (uv <= [camera.width, camera.height] + margin).all(1)
    return inside & (np.linalg.norm(xyz - middle, axis=1) <= FAR * spread)


def store_points(folder: Path, made: Triangulated) -> None:
    """Write `made` as the cache entry `folder`, replacing a damaged one; where the cache cannot be written, say so
    and go on without it."""
    points = io.BytesIO()
    np.savez(points, xyz=made.xyz, rgb=made.rgb)
    facts = json.dumps({"views": made.views, "seconds": round(made.seconds, 1),
                        "reprojection_error": made.reprojection_error})
    try:
        _remove_entry(folder)
        folder.mkdir(parents=True)
        write_hashed(folder / "points.npz", points.getvalue())
        write_hashed(folder / "facts.json", facts.encode())
    except (OSError, MCSplatError) as error:
        why = error.strerror if isinstance(error, OSError) and error.strerror else str(error)
        warnings.warn(f"cannot write the points cache {folder}: {why}; the points are used without being cached "
                      f"(set {CACHE_ENV} to a writable folder to keep them)", stacklevel=3)


def _remove_entry(folder: Path) -> None:
    """Clear the way for a new entry: a damaged one (a folder, or whatever took its place) goes, whole."""
    if folder.is_dir() and not folder.is_symlink():
        shutil.rmtree(folder)
    elif os.path.lexists(folder):
        folder.unlink()


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
    problem = implausible_points(xyz, rgb, views)  # what the cache checks, so that an entry it keeps is served
    if problem is not None:
        raise MCSplatError(f"triangulation from the known poses gave {problem} ({len(views)} views)")
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
