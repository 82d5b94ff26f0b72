"""What `mcsplat export` is asked, declared once: the command takes these fields as its options (the docstrings are
their help), the library the same value. The choice of Gaussians (selection.py) and the mesh's options
(mesh/options.py) are groups declared beside what reads them; their flags keep no prefix."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from ..io.formats.spz import DEFAULT_VERSION as DEFAULT_SPZ_VERSION
from ..mesh.options import MeshOptions
from .formats import FORMAT_NAMES, format_help
from .selection import SelectionOptions


@dataclass(frozen=True)
class ExportOptions:
    """Which file to write, and where."""

    # Checked where they are used (after the run is read), so that the errors come in the order they always did; the
    # mesh's own checks come as the options are made.

    # Its choices and help come from the table of export formats (formats.py): a new format adds no line here.
    format: Annotated[Literal[FORMAT_NAMES] | None, tyro.conf.arg(help=format_help())] = None
    out: Path | None = None
    """Output file, named .ply, .splat, .compressed.ply, .spz, .sog, .glb or .gltf (default: RUN/point_cloud.<that
    ending>); with --format mesh, .ply, .glb or .obj (default: RUN/mesh.ply)."""
    selection: Annotated[SelectionOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=SelectionOptions)
    spz_version: Literal[3, 4] = DEFAULT_SPZ_VERSION
    """spz: 3 (gzip, read by every .spz reader) or 4 (zstd, a little smaller; splat-transform and three.js read it,
    Spark 2.2 does not)."""
    mesh: Annotated[MeshOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=MeshOptions)
    device: Literal["auto", "cpu", "cuda"] = "auto"
