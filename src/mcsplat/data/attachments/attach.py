"""The seam: after a loader has made the scene, find each requested kind's files beside the photos, decode them and
bring each through what its image went through, then hang it on its view.

For one file: decoded at its own size (the kind), checked to have its image's shape, resized to the size the
undistortion starts from, undistorted with the image's own camera, and resized to the size the image is loaded at,
each step by the kind's resampling rule. Files are decoded in parallel (PIL and pycolmap release the GIL).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from .kind import Attachment, Kind
from .registry import kinds_for
from ..scene import Scene, View
from ...errors import DataError

ASPECT_TOLERANCE = 0.01  # a file may be stored at another size than its image, not at another shape


def attach(scene: Scene, requests: Sequence[object], workers: int | None = None) -> None:
    """Attach to the scene's views each kind that `requests` (MaskOptions, DepthOptions ...) asks for, and add each
    kind's note; a kind the scene has no files of is left out. Any problem is a one-line DataError."""
    views = scene.train + scene.test
    if any(view.source is None for view in views):
        raise ValueError("attach needs views made by a loader (View.source says where their pixels came from)")
    for kind, options in zip(kinds_for(requests), requests):
        found = kind.find(options, scene)
        if found is None:
            continue
        values = _load_all(kind, options, found.files, views, workers)
        kind.check(values, found, views, options)
        for view, value in zip(views, values):
            if value is not None:
                view.attachments[kind.name] = Attachment(kind, value)
        note = kind.note(values, found, options)
        if note:
            scene.notes.append(note)


def _load_all(kind: Kind, options: object, files: Sequence[Path | None], views: Sequence[View],
              workers: int | None) -> list[torch.Tensor | None]:
    workers = workers or min(8, os.cpu_count() or 1)

    def load(pair: tuple[Path | None, View]) -> torch.Tensor | None:
        file, view = pair
        return None if file is None else bring(kind, options, file, view)

    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"mcsplat-{kind.name}") as pool:
        return list(pool.map(load, zip(files, views)))


def bring(kind: Kind, options: object, file: Path, view: View) -> torch.Tensor:
    """The kind's values of `file` on the pixels of `view`'s image, as stored: [H, W] at the image's size."""
    values = kind.decode(file, view, options)
    source, resampling = view.source, kind.resampling
    height, width = values.shape[:2]
    expected_width, expected_height = source.before_undistortion
    if abs(width / height - expected_width / expected_height) > ASPECT_TOLERANCE * expected_width / expected_height:
        raise DataError(f"{kind.label} {file} is {width}x{height} but its image is {expected_width}x{expected_height}; "
                        f"a {kind.label} must have its image's shape")
    if (width, height) != tuple(source.before_undistortion):
        values = resampling.resize(values, source.before_undistortion)
    if source.undistort is not None:
        values = resampling.undistort(values, source.undistort)
    size = (view.camera.width, view.camera.height)
    if (values.shape[1], values.shape[0]) != size:
        values = resampling.resize(values, size)
    return torch.from_numpy(np.ascontiguousarray(values))
