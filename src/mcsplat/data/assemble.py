"""The part every loader shares: from the images it found and the cameras it read to a Scene.

A loader resolves each image to a Frame (file, name, intrinsics at the size it is loaded at, pose, and the
undistortion it needs, if any); `assemble` undistorts what needs it into the cache, puts the images behind one
ImageStore, makes the Views, splits train and test, keeps the finite SfM points and writes the notes.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from mcsplat.data import images, masks, undistort
from mcsplat.data.image_store import ImageStore, store_note
from mcsplat.data.masks import MaskJob, MaskOptions
from mcsplat.data.poses import make_camera
from mcsplat.data.scene import NAMED_BACKGROUNDS, Background, Scene, View, make_scene, split_every
from mcsplat.errors import DataError


@dataclass
class Frame:
    """One image as a loader resolved it."""

    path: Path                  # the image file
    name: str                   # the view's name (unique in the scene)
    K: np.ndarray               # 3x3 intrinsics for the image at `size`
    world_to_camera: np.ndarray  # 4x4, OpenCV axes
    size: tuple[int, int]       # (width, height) the image is loaded at
    undistort: undistort.Job | None = None  # a distorted image: undistorted into the cache, then loaded


@dataclass
class Points:
    """SfM points as read: float coordinates [P, 3] and uint8 RGB colours [P, 3], and where they came from."""

    xyz: np.ndarray
    rgb: np.ndarray
    source: str  # the file (or folder) named when points are dropped


def assemble(frames: Sequence[Frame], *, kind: str, root: Path, background: Background | None, test_every: int = 8,
             train_count: int | None = None, points: Points | None = None, notes: Sequence[str] = (),
             mask_options: MaskOptions | None = None) -> Scene:
    """The Scene of `frames`: with `train_count`, the first train_count frames are the training views and the rest
    the test views (a scene's own split); otherwise every `test_every`-th frame is a test view. Without a
    `background`, images with an alpha channel (a synthetic object on a transparent background, NeRF-Synthetic's
    convention) get white and the others black. `mask_options` says where the training masks come from (masks.py)."""
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
    keep, mask_notes = _masks(frames, root, mask_options or MaskOptions("none"), alpha)
    store = ImageStore(paths, [frame.size for frame in frames], background)
    views = [View(camera=make_camera(frame.K, frame.world_to_camera, *frame.size), image=store.handle(i),
                  name=frame.name, mask=keep[i] if keep else None) for i, frame in enumerate(frames)]
    if train_count is None:
        train, test = split_every(views, test_every)
    else:
        train, test = views[:train_count], views[train_count:]
    if not train:
        what = "its 1 view is" if len(views) == 1 else f"each of its {len(views)} views is"
        raise DataError(f"{root}: {what} a test view, which leaves none to train on; a scene needs at least 2 views "
                        "(one to train on, one to test) and --test-every 0 or above 1 (0: train on every view)")
    notes += store_note(store) + mask_notes
    xyz, rgb = _finite(points) if points is not None else (None, None)
    return make_scene(train, test, xyz, rgb, background, kind, root, notes=notes, alpha=alpha)


def _finite(points: Points) -> tuple[torch.Tensor, torch.Tensor]:
    """The points without NaN/inf coordinates (warning when some are dropped), as float32 tensors in [0, 1]."""
    finite = np.isfinite(points.xyz).all(axis=1)
    if not finite.all():
        warnings.warn(f"{points.source}: dropping {int((~finite).sum())} SfM points with NaN/inf coordinates",
                      stacklevel=4)
    return (torch.from_numpy(points.xyz[finite].astype(np.float32)),
            torch.from_numpy(points.rgb[finite].astype(np.float32) / 255.0))


def _masks(frames: Sequence[Frame], root: Path, options: MaskOptions, alpha: bool
           ) -> tuple[list[torch.Tensor] | None, list[str]]:
    """Each frame's mask (masks.py) and the note that says where they came from; None when the scene has none."""
    if options.source == "alpha":
        if not alpha:
            raise DataError(f"--masks alpha: the images of {root} have no alpha channel; give a folder of masks "
                            "or --masks none")
        sources, where = [(frame.path, True) for frame in frames], "the images' alpha channel"
    else:
        folder = options.folder(root)
        if folder is None:
            if options.invert:
                raise DataError(f"--invert-masks: {root} has no {masks.MASK_FOLDER}/ folder, so there are no masks to "
                                "invert; give the masks' folder with --masks, or leave --invert-masks out")
            return None, []
        files = [masks.mask_file(folder, frame.name, frame.path) for frame in frames]
        missing = [frame.name for frame, file in zip(frames, files) if file is None]
        if missing:
            raise masks.missing_error(folder, missing, len(frames))
        sources, where = [(file, False) for file in files], str(folder)
    jobs = [MaskJob(source, _file_size(frame), frame.undistort, frame.size, is_alpha)
            for frame, (source, is_alpha) in zip(frames, sources)]
    keep = masks.load_masks(jobs, options.invert)
    masks.check_something_kept(keep, jobs, [frame.name for frame in frames], where, options.invert)
    return keep, [masks.describe(keep, where + (", inverted" if options.invert else ""))]


def _file_size(frame: Frame) -> tuple[int, int]:
    """The size the frame's image file has (a distorted one: its camera's), which its mask is brought to first."""
    if frame.undistort is not None:
        return frame.undistort.camera.width, frame.undistort.camera.height
    return frame.size
