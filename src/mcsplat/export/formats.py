"""Everything `mcsplat export` writes, in one table: each Gaussian format of io/formats (the 3DGS .ply, .splat,
PlayCanvas compressed .ply, Niantic .spz, PlayCanvas .sog, glTF), which takes the choice of Gaussians (selection.py),
and the mesh.

A new Gaussian format is its module in io/formats/ and its entry in io/formats' FORMATS: it appears here on its own.
Another kind of output (as the mesh) is its module in this package and its entry below. The CLI takes --format's
choices and help from here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from ..io.formats import FORMATS, GaussianFormat
from .gaussians import export_gaussians
from .job import ExportJob
from .mesh import check_mesh_file, export_mesh

if TYPE_CHECKING:
    from ..run.folder import RunDir

DEFAULT_FORMAT = "ply"  # without --format, and an --out that names none


@dataclass(frozen=True)
class ExportFormat:
    """One thing `mcsplat export` writes."""

    name: str                               # --format's value
    summary: str                            # its sentence in --format's help
    default_file: Callable[[RunDir], Path]  # where it goes without --out
    write: Callable[[ExportJob], None]      # makes the file from the run read back, and says what it wrote
    ending: str | None = None               # an --out name ending so chooses it without --format (None: --format only)
    check_path: Callable[[Path], None] | None = None  # refuses, in one line, a file it cannot be written as
    companions: Callable[[Path], tuple[Path, ...]] = lambda path: ()  # the files written beside it (a .gltf's .bin)
    reads: frozenset[str] = frozenset()     # the fields of ExportOptions it reads (a group by its name: selection,
    #                                         mesh), beyond those every format reads


def _gaussian_format(codec: GaussianFormat) -> ExportFormat:
    settings = {"spz_version"} & set(codec.settings)  # the write settings that are options (not antialiased)
    return ExportFormat(codec.name, codec.summary, default_file=lambda folder: folder.export_file(codec.ending),
                        write=functools.partial(export_gaussians, codec), ending=codec.ending,
                        check_path=codec.check_path, companions=codec.companions,
                        reads=frozenset({"selection"}) | settings)


# Only --format chooses the mesh: its .ply would read as a 3DGS .ply by the ending.
MESH = ExportFormat("mesh", "the surface the training views see (median depth fused into a signed distance volume, "
                    "marching cubes), with vertex colours.", default_file=lambda folder: folder.mesh_file,
                    write=export_mesh, check_path=check_mesh_file, reads=frozenset({"mesh"}))

EXPORT_FORMATS: dict[str, ExportFormat] = {entry.name: entry for entry in (*map(_gaussian_format, FORMATS.values()),
                                                                           MESH)}
FORMAT_NAMES = tuple(EXPORT_FORMATS)


def format_help() -> str:
    """--format's help: the formats an --out name chooses, the default, then those only --format chooses."""
    by_ending = [f"{entry.name}: {entry.summary}" for entry in EXPORT_FORMATS.values() if entry.ending is not None]
    by_name = [f"{entry.name}: {entry.summary}" for entry in EXPORT_FORMATS.values() if entry.ending is None]
    return " ".join([*by_ending, f"Default: the one --out's name ends with, else {DEFAULT_FORMAT}.", *by_name])
