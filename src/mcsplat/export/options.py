"""What `mcsplat export` is asked: the options of cli.Export but the run folder, with the same defaults."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..gaussians import DEAD_OPACITY
from ..io.formats.spz import DEFAULT_VERSION as DEFAULT_SPZ_VERSION


@dataclass(frozen=True)
class ExportOptions:
    """Checked where they are used (after the run is read), so that the errors come in the order they always did."""

    format: str | None = None         # a name of formats.EXPORT_FORMATS; None: the one --out's name ends with, else ply
    out: Path | None = None           # the file to write; None: the format's default file in the run folder
    # Which Gaussians a Gaussian format holds (selection.py)
    min_opacity: float = DEAD_OPACITY  # the dead ones MCMC relocates are left out
    max_gaussians: int | None = None  # at most this many, those that contribute most
    prune: bool = False               # leave out those no training view shows
    max_scale: float | None = None    # scene radii
    max_distance: float | None = None  # scene radii from the training cameras' centre
    spz_version: int = DEFAULT_SPZ_VERSION  # the .spz container: 3 (gzip) or 4 (zstd)
    # The mesh (mesh.py; mesh/extract.py's MeshOptions)
    voxel_size: float | None = None
    voxel_budget: int = 1 << 24
    alpha_min: float = 0.5
    min_component: float = 0.02
    depth: str = "median"             # "median" or "planar"
    truncation: float = 4.0           # voxels
    consistent_views: int = 4         # of the 6 nearest views, how many must confirm a pixel's depth
    device: str = "auto"              # "auto", "cpu" or "cuda"


# The options only some formats read (export/formats.py's `reads`); format, out and device every format reads.
SELECTION_OPTIONS = ("min_opacity", "max_gaussians", "prune", "max_scale", "max_distance")  # the Gaussian formats
MESH_OPTIONS = ("voxel_size", "voxel_budget", "alpha_min", "min_component", "depth", "truncation",
                "consistent_views")
