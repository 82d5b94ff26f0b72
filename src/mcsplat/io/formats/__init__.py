"""Gaussians in the file formats that viewers read: the 3DGS `.ply`, `.splat`, PlayCanvas compressed `.ply`,
Niantic `.spz` (versions 3 and 4), PlayCanvas `.sog`, glTF's KHR_gaussian_splatting (`.glb`, `.gltf`); one table of
them (FORMATS), which `mcsplat export` offers as they are (export/formats.py).

Every writer takes the model's raw parameters as numpy arrays (the keys of GaussianModel.params: means, log_scales,
quats (w, x, y, z), opacity_logits, sh0 [N,1,3], shN [N,K-1,3]) and writes atomically; every reader returns the same
keys, decoded (within the format's quantisation), so that tests and tools can read a file back. The byte layout of
each format is in its module's docstring; the plain 3DGS .ply's in io/ply.py (plain_ply.py fits it to the table).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import compressed_ply, gltf, plain_ply, sog, splat, spz
from .prune import select_gaussians

__all__ = ["GaussianFormat", "FORMATS", "EXTENSIONS", "select_gaussians", "write_gaussians", "read_gaussians",
           "format_named_by"]

Params = dict[str, np.ndarray]


@dataclass(frozen=True)
class GaussianFormat:
    """One file format of Gaussians."""

    name: str                      # what `mcsplat export --format` calls it
    ending: str                    # what its files' names end with (the longest ending that matches decides)
    summary: str                   # its sentence in --format's help: who reads it, how large it is
    write: Callable[..., None]     # (path, params), and the keyword settings it takes
    read: Callable[[Path], Params]
    # The keyword settings of write_gaussians its writer takes: "antialiased" (the file can say that the scene is
    # drawn with the 2D filter), "spz_version".
    settings: tuple[str, ...] = ()
    companions: Callable[[Path], tuple[Path, ...]] = lambda path: ()  # the other files written beside it (a .bin)
    check_path: Callable[[Path], None] | None = None  # refuses, in one line, a file it must not be written as

    @property
    def records_antialiasing(self) -> bool:
        return "antialiased" in self.settings


FORMATS: dict[str, GaussianFormat] = {entry.name: entry for entry in (
    GaussianFormat("ply", ".ply", "every viewer, full SH.", plain_ply.write_plain_ply, plain_ply.read_plain_ply),
    GaussianFormat("splat", ".splat", "32 bytes each, no SH.", splat.write_splat, splat.read_splat),
    GaussianFormat("compressed-ply", ".compressed.ply", "SuperSplat/PlayCanvas, ~4x smaller.",
                   compressed_ply.write_compressed_ply, compressed_ply.read_compressed_ply),
    GaussianFormat("spz", ".spz", f"Niantic's format, ~10x smaller: version 3 (gzip, every reader) or 4 (zstd, "
                   f"newer readers), --spz-version (default {spz.DEFAULT_VERSION}).", spz.write_spz, spz.read_spz,
                   settings=("antialiased", "spz_version")),
    GaussianFormat("sog", ".sog", "PlayCanvas SOG, WebP images of quantised attributes in a zip (SuperSplat, "
                   "PlayCanvas, Spark), ~15x smaller.", sog.write_sog, sog.read_sog, settings=("antialiased",)),
    GaussianFormat("glb", ".glb", "glTF binary, Khronos KHR_gaussian_splatting (three.js, Babylon.js, PlayCanvas), "
                   "full SH, float32.", gltf.write_glb, gltf.read_glb),
    GaussianFormat("gltf", ".gltf", "the same as glTF JSON with its buffer in a .bin beside it.",
                   gltf.write_gltf, gltf.read_gltf, companions=lambda path: (gltf.bin_file_of(path),),
                   check_path=gltf.check_buffer_file),
)}
EXTENSIONS = {name: entry.ending for name, entry in FORMATS.items()}


def write_gaussians(format_name: str, path: str | os.PathLike, params: Params, *, antialiased: bool = False,
                    spz_version: int = spz.DEFAULT_VERSION) -> None:
    """`antialiased`: the scene was trained to be drawn with the 2D filter; written where the format records it.
    `spz_version`: the .spz container (3: gzip, 4: zstd); the other formats have one layout."""
    entry = FORMATS[format_name]
    offered = {"antialiased": antialiased, "spz_version": spz_version}
    entry.write(Path(path), params, **{name: offered[name] for name in entry.settings})


def read_gaussians(format_name: str, path: str | os.PathLike) -> Params:
    return FORMATS[format_name].read(Path(path))


def format_named_by(path: str | os.PathLike) -> str | None:
    """The format whose ending `path`'s name has (the longest that matches: x.compressed.ply is compressed-ply,
    x.ply ply), None for none."""
    name = Path(path).name.lower()
    matching = [(len(entry.ending), entry.name) for entry in FORMATS.values() if name.endswith(entry.ending)]
    return max(matching)[1] if matching else None
