"""Gaussians in the file formats that web viewers read: `.splat`, PlayCanvas compressed `.ply`, Niantic `.spz`.

Every writer takes the model's raw parameters as numpy arrays (the keys of GaussianModel.params: means, log_scales,
quats (w, x, y, z), opacity_logits, sh0 [N,1,3], shN [N,K-1,3]) and writes atomically; every reader returns the same
keys, decoded (within the format's quantisation), so that tests and tools can read a file back. The byte layout of
each format is in its module's docstring. The plain 3DGS .ply is io/ply.py.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from . import compressed_ply, splat, spz
from .prune import select_gaussians

__all__ = ["FORMATS", "EXTENSIONS", "ENDINGS", "format_named_by", "select_gaussians", "write_gaussians",
           "read_gaussians"]

# name -> (writer, reader, default file name ending)
FORMATS: dict[str, tuple[Callable, Callable, str]] = {
    "splat": (splat.write_splat, splat.read_splat, ".splat"),
    "compressed-ply": (compressed_ply.write_compressed_ply, compressed_ply.read_compressed_ply, ".compressed.ply"),
    "spz": (spz.write_spz, spz.read_spz, ".spz"),
}
EXTENSIONS = {name: ending for name, (_, _, ending) in FORMATS.items()}
ENDINGS = {"ply": ".ply", **EXTENSIONS}  # every export format, the plain 3DGS .ply included


def format_named_by(path: str | os.PathLike) -> str | None:
    """The export format a file name asks for by its ending (the longest that matches: x.compressed.ply is
    compressed-ply, x.ply ply), or None."""
    name = Path(path).name.lower()
    matching = [(len(ending), fmt) for fmt, ending in ENDINGS.items() if name.endswith(ending)]
    return max(matching)[1] if matching else None


def write_gaussians(format_name: str, path: str | os.PathLike, params: dict[str, np.ndarray], *,
                    antialiased: bool = False) -> None:
    """`antialiased`: the scene was trained to be drawn with the 2D filter; only .spz has a flag that says so."""
    if format_name == "spz":
        spz.write_spz(Path(path), params, antialiased=antialiased)
    else:
        FORMATS[format_name][0](Path(path), params)


def read_gaussians(format_name: str, path: str | os.PathLike) -> dict[str, np.ndarray]:
    return FORMATS[format_name][1](Path(path))
