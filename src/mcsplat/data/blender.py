"""Blender / NeRF-synthetic scenes (transforms_{train,test}.json) and instant-ngp / nerfstudio transforms.json."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from mcsplat.data import images
from mcsplat.data.poses import intrinsic_matrix, make_camera, opengl_c2w_to_opencv_w2c, scale_intrinsics
from mcsplat.data.scene import Background, Scene, View, make_scene, split_every
from mcsplat.errors import DataError

SPLIT_FILES = ("transforms_train.json", "transforms_test.json", "transforms_val.json")
SINGLE_FILE = "transforms.json"
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")  # OPENCV is fine when its distortion terms are zero


def is_blender(root: Path) -> bool:
    return (root / SPLIT_FILES[0]).is_file() or (root / SINGLE_FILE).is_file()


def read_json(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"{path} is not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno}); fix or "
                        "regenerate the file") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DataError(f"{path} has no 'frames' list; a NeRF transforms file is an object with 'frames': "
                        "[{'file_path': ..., 'transform_matrix': ...}, ...]")
    return data


class _Frame:
    """One frame of a transforms file, resolved: image path, pose, intrinsics (possibly partly unknown)."""

    def __init__(self, path: Path, name: str, w2c: np.ndarray, meta: dict[str, Any]):
        self.path, self.name, self.w2c, self.meta = path, name, w2c, meta


def _number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _frames(path: Path, data: dict[str, Any], root: Path, skip_missing: bool) -> list[_Frame]:
    keys = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y", "camera_model",
            *_DISTORTION_KEYS)
    top = {k: data[k] for k in keys if k in data}
    frames, missing = [], []
    for index, frame in enumerate(data["frames"]):
        where = f"{path} frame {index}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise DataError(f"{where} has no 'file_path' string")
        if "transform_matrix" not in frame:
            raise DataError(f"{where} ('{frame['file_path']}') has no 'transform_matrix'")
        try:
            matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise DataError(f"{where} ('{frame['file_path']}'): transform_matrix is not a matrix of numbers") from None
        w2c = opengl_c2w_to_opencv_w2c(matrix, f"{where} ('{frame['file_path']}') transform_matrix")
        image = images.find_image(path.parent / frame["file_path"])
        if image is None:
            missing.append(frame["file_path"])
            continue
        meta = dict(top)
        meta.update({k: frame[k] for k in keys if k in frame})
        name = image.relative_to(root).with_suffix("") if image.is_relative_to(root) else Path(image.stem)
        frames.append(_Frame(image, str(PurePosixPath(name)), w2c, meta))
    if missing and not skip_missing:
        raise DataError(f"image '{missing[0]}' listed in {path} is missing ({path.parent / missing[0]}[.png] does "
                        f"not exist)" + (f", and {len(missing) - 1} more" if len(missing) > 1 else ""))
    if missing:
        if not frames:
            raise DataError(f"none of the {len(missing)} images listed in {path} exist (first: "
                            f"{path.parent / missing[0]})")
        warnings.warn(f"{path}: skipping {len(missing)} frames whose image is missing: "
                      f"{', '.join(missing[:5])}" + (" ..." if len(missing) > 5 else ""), stacklevel=4)
    if not frames:
        raise DataError(f"{path} lists no frames")
    return frames


def _intrinsics(frame: _Frame, size: tuple[int, int], source: Path) -> np.ndarray:
    """K for the image at its file size, from fl_x/fl_y/cx/cy (or camera_angle_x/_y); checks w/h and distortion."""
    meta, where = frame.meta, f"{source} ('{frame.path.name}')"
    model = meta.get("camera_model")
    if model is not None and model not in _PINHOLE_MODELS:
        raise DataError(f"{where}: camera_model {model} is not supported (pinhole only); undistort the images and "
                        "write a pinhole transforms file (e.g. ns-process-data, or colmap image_undistorter)")
    distortion = {k: _number(meta[k], k, where) for k in _DISTORTION_KEYS if k in meta}
    if any(v != 0.0 for v in distortion.values()):
        raise DataError(f"{where} has lens distortion ({', '.join(f'{k}={v:g}' for k, v in distortion.items())}), "
                        "which mcsplat does not support; undistort the images first (colmap image_undistorter)")
    width, height = size
    if "w" in meta or "h" in meta:
        stated = (round(_number(meta.get("w", width), "w", where)), round(_number(meta.get("h", height), "h", where)))
        if stated != size:
            raise DataError(f"image {frame.path} is {width}x{height} but {source} says w={stated[0]}, h={stated[1]}; "
                            "all images must have the size of their camera")
    if "fl_x" in meta:
        fx = _number(meta["fl_x"], "fl_x", where)
        fy = _number(meta["fl_y"], "fl_y", where) if "fl_y" in meta else fx
    elif "camera_angle_x" in meta:
        fx = 0.5 * width / math.tan(0.5 * _number(meta["camera_angle_x"], "camera_angle_x", where))
        fy = 0.5 * height / math.tan(0.5 * _number(meta["camera_angle_y"], "camera_angle_y", where)) \
            if "camera_angle_y" in meta else fx
    else:
        raise DataError(f"{where} has no focal length: give camera_angle_x (radians) or fl_x/fl_y (pixels)")
    if not (fx > 0 and fy > 0):
        raise DataError(f"{where}: the focal length must be positive (fl_x={fx:g}, fl_y={fy:g})")
    cx = _number(meta["cx"], "cx", where) if "cx" in meta else width / 2
    cy = _number(meta["cy"], "cy", where) if "cy" in meta else height / 2
    return intrinsic_matrix(fx, fy, cx, cy)


def _views(frames: list[_Frame], sources: list[Path], downscale: int, background: Background) -> list[View]:
    sizes = images.probe_sizes([f.path for f in frames])
    first_size, first = sizes[0], frames[0]
    intrinsics, targets = [], []
    for frame, size, source in zip(frames, sizes, sources):
        explicit = "w" in frame.meta or "h" in frame.meta
        if not explicit and size != first_size:
            raise DataError(f"image {frame.path} is {size[0]}x{size[1]} but {first.path} is "
                            f"{first_size[0]}x{first_size[1]}; all images of a Blender scene must have one size")
        K = _intrinsics(frame, size, source)
        target = images.downscaled_size(*size, downscale)
        intrinsics.append(scale_intrinsics(K, size, target))
        targets.append(target)
    pixels = images.load_images([f.path for f in frames], targets, background)
    return [View(camera=make_camera(K, f.w2c, *t), image=p, name=f.name)
            for f, K, t, p in zip(frames, intrinsics, targets, pixels)]


def load_blender(root: Path, downscale: int, background: Background, test_every: int) -> Scene:
    notes = []
    if (root / SPLIT_FILES[0]).is_file():
        train_file = root / SPLIT_FILES[0]
        test_file = next((root / f for f in SPLIT_FILES[1:] if (root / f).is_file()), None)
        train_frames = _frames(train_file, read_json(train_file), root, skip_missing=False)
        if test_file is not None:
            test_frames = _frames(test_file, read_json(test_file), root, skip_missing=False)
            notes.append(f"splits from {train_file.name} and {test_file.name}")
        else:
            train_frames, test_frames = split_every(train_frames, test_every)
            notes.append(f"no transforms_test.json or transforms_val.json: every {test_every}th frame is a test view"
                         if test_every else "no test split")
        frames = train_frames + test_frames
        sources = [train_file] * len(train_frames) + [test_file or train_file] * len(test_frames)
    else:
        single = root / SINGLE_FILE
        frames = sorted(_frames(single, read_json(single), root, skip_missing=True), key=lambda f: f.name)
        sources = [single] * len(frames)
        train_frames, test_frames = split_every(frames, test_every)
        frames = train_frames + test_frames
        notes.append(f"frames from {single.name}; " + (f"every {test_every}th is a test view" if test_every
                                                         else "no test split"))
    views = _views(frames, sources, downscale, background)
    if downscale > 1:
        notes.append(f"images resized to 1/{downscale}")
    return make_scene(views[:len(train_frames)], views[len(train_frames):], None, None, background, "blender", root,
                      notes=notes)
