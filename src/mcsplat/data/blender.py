"""Blender / NeRF-synthetic scenes (transforms_{train,test}.json) and instant-ngp / nerfstudio transforms.json."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from . import images, undistort
from .assemble import Frame, assemble
from .poses import intrinsic_matrix, opengl_c2w_to_opencv_w2c, scale_intrinsics
from .scene import Background, Scene
from ..errors import DataError

SPLIT_FILES = ("transforms_train.json", "transforms_test.json", "transforms_val.json")
SINGLE_FILE = "transforms.json"
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_DISTORTED_MODELS = ("OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")


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


class _ListedFrame:
    """One frame of a transforms file, resolved: image path, pose, intrinsics (possibly partly unknown)."""

    def __init__(self, path: Path, name: str, w2c: np.ndarray, meta: dict[str, Any]):
        self.path, self.name, self.w2c, self.meta = path, name, w2c, meta


def _number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DataError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _frames(path: Path, data: dict[str, Any], root: Path, skip_missing: bool) -> list[_ListedFrame]:
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
        frames.append(_ListedFrame(image, str(PurePosixPath(name)), w2c, meta))
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


def _distortion(frame: _ListedFrame, source: Path) -> tuple[str, list[float]] | None:
    """(COLMAP model name, its distortion parameters) of a frame, or None for a pinhole camera.

    nerfstudio's convention: k1..k4 radial, p1, p2 tangential; OPENCV (k1, k2, p1, p2), FULL_OPENCV when k3 is set
    (k3 is OpenCV's r^6 term), OPENCV_FISHEYE (k1..k4, no tangential terms).
    """
    meta, where = frame.meta, f"{source} ('{frame.path.name}')"
    model = meta.get("camera_model")
    known = _PINHOLE_MODELS + _DISTORTED_MODELS
    if model is not None and model not in known:
        raise DataError(f"{where}: camera_model {model!r} is not supported (use one of {', '.join(known)}); "
                        "undistort the images with the tool that made them and write a PINHOLE transforms file")
    d = {k: _number(meta[k], k, where) if k in meta else 0.0 for k in _DISTORTION_KEYS}
    if model == "OPENCV_FISHEYE":
        if d["p1"] or d["p2"]:
            raise DataError(f"{where}: camera_model OPENCV_FISHEYE has no tangential terms, but p1={d['p1']:g}, "
                            f"p2={d['p2']:g}; remove them or use camera_model OPENCV")
        return "OPENCV_FISHEYE", [d["k1"], d["k2"], d["k3"], d["k4"]]
    if not any(d.values()):
        return None
    if model in _PINHOLE_MODELS:
        raise DataError(f"{where}: camera_model {model} but distortion terms are set "
                        f"({', '.join(f'{k}={v:g}' for k, v in d.items() if v)}); set camera_model OPENCV (or remove "
                        "the terms if the images are already undistorted)")
    if d["k4"]:
        raise DataError(f"{where}: k4={d['k4']:g} with a perspective (OPENCV) camera is not a model COLMAP knows; "
                        "use camera_model OPENCV_FISHEYE if the lens is a fisheye, else undistort the images first")
    if d["k3"] or model == "FULL_OPENCV":
        return "FULL_OPENCV", [d["k1"], d["k2"], d["p1"], d["p2"], d["k3"], 0.0, 0.0, 0.0]
    return "OPENCV", [d["k1"], d["k2"], d["p1"], d["p2"]]


def _intrinsics(frame: _ListedFrame, size: tuple[int, int], source: Path) -> np.ndarray:
    """K for the image at its file size, from fl_x/fl_y/cx/cy (or camera_angle_x/_y); checks w/h."""
    meta, where = frame.meta, f"{source} ('{frame.path.name}')"
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


def _resolved(frames: list[_ListedFrame], sources: list[Path], downscale: int) -> list[Frame]:
    """Each frame's image file, intrinsics at its loaded size, pose, and undistortion where its camera has lens
    distortion (one pinhole camera per distinct distorted camera)."""
    sizes = images.probe_sizes([f.path for f in frames])
    first_size, first = sizes[0], frames[0]
    resolved = []
    pinholes: dict[tuple, Any] = {}
    for frame, size, source in zip(frames, sizes, sources):
        explicit = "w" in frame.meta or "h" in frame.meta
        if not explicit and size != first_size:
            raise DataError(f"image {frame.path} is {size[0]}x{size[1]} but {first.path} is "
                            f"{first_size[0]}x{first_size[1]}; all images of a Blender scene must have one size")
        K = _intrinsics(frame, size, source)
        distortion = _distortion(frame, source)
        job = None
        if distortion is not None:
            import pycolmap

            model, extra = distortion
            params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *extra]
            key = (model, size, tuple(params))
            if key not in pinholes:
                camera = pycolmap.Camera(model=model, width=size[0], height=size[1], params=params)
                pinholes[key] = (camera, undistort.pinhole_camera(camera, f"{source} ('{frame.path.name}')"))
            camera, pinhole = pinholes[key]
            size = (pinhole.width, pinhole.height)
            K = intrinsic_matrix(*pinhole.params[:4])
        target = images.downscaled_size(*size, downscale)
        if distortion is not None:
            job = undistort.Job(frame.path, camera, pinhole, target)
        resolved.append(Frame(frame.path, frame.name, scale_intrinsics(K, size, target), frame.w2c, target, job))
    return resolved


def load_blender(root: Path, downscale: int, background: Background | None, test_every: int) -> Scene:
    notes = []
    if (root / SPLIT_FILES[0]).is_file():
        train_file = root / SPLIT_FILES[0]
        test_file = next((root / f for f in SPLIT_FILES[1:] if (root / f).is_file()), None)
        train_frames = _frames(train_file, read_json(train_file), root, skip_missing=False)
        test_frames = [] if test_file is None else _frames(test_file, read_json(test_file), root, skip_missing=False)
        if test_file is not None:
            notes.append(f"splits from {train_file.name} and {test_file.name}")
            train_count: int | None = len(train_frames)
        else:
            notes.append(f"no transforms_test.json or transforms_val.json: every {test_every}th frame is a test view"
                         if test_every else "no test split")
            train_count = None  # assemble splits, once the repeated images are out
        frames = train_frames + test_frames
        sources = [train_file] * len(train_frames) + [test_file] * len(test_frames)
    else:
        single = root / SINGLE_FILE
        frames = sorted(_frames(single, read_json(single), root, skip_missing=True), key=lambda f: f.name)
        sources = [single] * len(frames)
        train_count = None
        notes.append(f"frames from {single.name}; " + (f"every {test_every}th is a test view" if test_every
                                                         else "no test split"))
    if downscale > 1:
        notes.append(f"images resized to 1/{downscale}")
    return assemble(_resolved(frames, sources, downscale), kind="blender", root=root, background=background,
                    test_every=test_every, train_count=train_count, notes=notes)
