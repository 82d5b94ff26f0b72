"""A scene's cameras as an instant-ngp / nerfstudio transforms.json: per frame the image file, the intrinsics (fl_x,
fl_y, cx, cy, w, h) and the camera-to-world matrix in OpenGL axes (x right, y up, looking along -z). It is how a
capture with poses but no points reaches mcsplat from instant-ngp, nerfstudio or Polycam, and how the benchmarks make
such scenes from the shared COLMAP captures."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np

from ..camera import Camera
from .atomic import atomic_write_text

_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


class Frame(Protocol):
    """What a frame is written from; a data.View has it. A protocol, so that io/ does not import data/, which writes
    through io/ (docs/architecture.md, "The layers")."""

    @property
    def name(self) -> str: ...

    @property
    def camera(self) -> Camera: ...

    @property
    def image_file(self) -> Path | None: ...


def write_transforms(views: Sequence[Frame], path: str | os.PathLike) -> None:
    """Write `views` (their image files as they are, by absolute path) to the transforms.json at `path`."""
    frames = []
    for view in views:
        if view.image_file is None:
            raise ValueError(f"view {view.name} has no image file to refer to")
        camera = view.camera
        w2c = camera.world_to_camera.double().numpy()
        c2w = np.eye(4)
        c2w[:3, :3] = w2c[:3, :3].T @ _CV_TO_GL
        c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
        frames.append({"file_path": str(Path(view.image_file).resolve()), "transform_matrix": c2w.tolist(),
                       "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
                       "w": camera.width, "h": camera.height})
    atomic_write_text(path, json.dumps({"frames": frames}, indent=1) + "\n")
