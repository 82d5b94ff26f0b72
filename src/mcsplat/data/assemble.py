"""The part every loader shares: from the images it found and the cameras it read to a Scene.

A loader resolves each image to a Frame (file, name, intrinsics at the size it is loaded at, pose, and the
undistortion it needs, if any); `assemble` undistorts what needs it into the cache, puts the images behind one
ImageStore, makes the Views, splits train and test, keeps the finite SfM points and writes the notes. Each View keeps
where its pixels came from (scene.ImageSource), so that what lies beside its photo (data/attachments/: masks, depth
maps) can be found and brought to it after the loader is done, without the loader knowing of it.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from . import images, repeats, undistort
from .image_store import ImageStore, store_note
from .poses import make_camera
from .scene import NAMED_BACKGROUNDS, Background, ImageSource, Scene, View, make_scene, split_every
from ..errors import DataError


@dataclass
class Frame:
    """One image as a loader resolved it."""

    path: Path                  # the image file
    name: str                   # the view's name (unique in the scene)
    K: np.ndarray               # 3x3 intrinsics for the image at `size`
    world_to_camera: np.ndarray  # 4x4, OpenCV axes
    size: tuple[int, int]       # (width, height) the image is loaded at
    undistort: undistort.Job | None = None  # a distorted image: undistorted into the cache, then loaded
    units: float = 1.0          # scene units per unit of the capture (1 unless the loader rescales the world)


@dataclass
class Points:
    """SfM points as read: float coordinates [P, 3] and uint8 RGB colours [P, 3], and where they came from."""

    xyz: np.ndarray
    rgb: np.ndarray
    source: str  # the file (or folder) named when points are dropped


def assemble(frames: Sequence[Frame], *, kind: str, root: Path, background: Background | None, test_every: int = 8,
             train_count: int | None = None, points: Points | None = None, notes: Sequence[str] = ()) -> Scene:
    """The Scene of `frames`: with `train_count`, the first train_count frames are the training views and the rest
    the test views (a scene's own split); otherwise every `test_every`-th frame is a test view. A frame whose image
    repeats one before it is left out, with a warning (repeats.py). Without a `background`, images with an alpha
    channel (a synthetic object on a transparent background, NeRF-Synthetic's convention) get white and the others
    black."""
    frames, train_count = _distinct(frames, root, train_count)
    paths = [frame.path for frame in frames]
    alpha = any(images.has_alpha(path) for path in paths)
    if background is None:
        background = NAMED_BACKGROUNDS["white" if alpha else "black"]
    jobs = [frame.undistort for frame in frames if frame.undistort is not None]
    notes = list(notes)
    if jobs:
        cached = iter(undistort.undistort_to_cache(jobs, background))
        paths = [next(cached) if frame.undistort is not None else path for frame, path in zip(frames, paths)]
        models = sorted({job.camera.model.name for job in jobs})
        notes.append(f"{len(jobs)} images with {'/'.join(models)} cameras undistorted to PINHOLE (cached in "
                     f"{undistort.cache_root()})")
    store = ImageStore(paths, [frame.size for frame in frames], background)
    views = [View(camera=make_camera(frame.K, frame.world_to_camera, *frame.size), image=store.handle(i),
                  name=frame.name, source=_source(frame)) for i, frame in enumerate(frames)]
    if train_count is None:
        train, test = split_every(views, test_every)
    else:
        train, test = views[:train_count], views[train_count:]
    if not train:
        what = "its 1 view is" if len(views) == 1 else f"each of its {len(views)} views is"
        raise DataError(f"{root}: {what} a test view, which leaves none to train on; a scene needs at least 2 views "
                        "(one to train on, one to test) and --test-every 0 or above 1 (0: train on every view)")
    notes += store_note(store)
    xyz, rgb = _finite(points) if points is not None else (None, None)
    return make_scene(train, test, xyz, rgb, background, kind, root, notes=notes, alpha=alpha)


def _distinct(frames: Sequence[Frame], root: Path, train_count: int | None) -> tuple[list[Frame], int | None]:
    """The frames without those whose image repeats an earlier frame's (the training frames come first, so a test
    frame that repeats a training image is the one left out), and the training frames' count among them."""
    kept, repeated = repeats.first_copies([frame.path for frame in frames])
    if repeated:
        def shown(frame: Frame) -> str:
            return str(frame.path.relative_to(root)) if frame.path.is_relative_to(root) else str(frame.path)

        named = [repeats.describe(shown(frames[copy]), shown(frames[original])) for copy, original in repeated.items()]
        count = f"{len(named)} images repeat" if len(named) > 1 else "1 image repeats"
        more = " ..." if len(named) > 5 else ""
        warnings.warn(f"{root}: {count} an image listed before ({', '.join(named[:5])}{more}); each image is used "
                      "once, so that no view is trained on twice or both trained on and tested", stacklevel=4)
    if train_count is not None:
        train_count = sum(1 for index in kept if index < train_count)
    return [frames[index] for index in kept], train_count


def _finite(points: Points) -> tuple[torch.Tensor, torch.Tensor]:
    """The points without NaN/inf coordinates (warning when some are dropped), as float32 tensors in [0, 1]."""
    finite = np.isfinite(points.xyz).all(axis=1)
    if not finite.all():
        warnings.warn(f"{points.source}: dropping {int((~finite).sum())} SfM points with NaN/inf coordinates",
                      stacklevel=4)
    return (torch.from_numpy(points.xyz[finite].astype(np.float32)),
            torch.from_numpy(points.rgb[finite].astype(np.float32) / 255.0))


def _source(frame: Frame) -> ImageSource:
    """Where the frame's pixels came from: its photo, the size its undistortion starts from (the distorted camera's;
    a pinhole frame's loaded size), that undistortion and the loader's units."""
    first = (frame.undistort.camera.width, frame.undistort.camera.height) if frame.undistort else frame.size
    return ImageSource(frame.path, first, frame.undistort, frame.units)
