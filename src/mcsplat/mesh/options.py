"""How a mesh is made: `MeshOptions`, declared once. `extract()` reads it and `mcsplat export --format mesh` takes its
fields as options (the docstrings are their help), so a default changes here alone.

This module is light on purpose (no torch): the CLI imports it to build its options.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import tyro

from ..errors import MCSplatError

DEFAULT_VOXEL_BUDGET = 1 << 24  # 256^3
# The depth of a view that is fused. median: where the ray meets the density peak of the Gaussian at which the
# accumulated alpha reaches 0.5 (2DGS, GOF, RaDe-GS). planar: where it meets the composited plane of the Gaussians
# (PGSR's unbiased depth), which follows a flat Gaussian's slant across all its pixels; meant for --surface runs,
# whose Gaussians are flat (on round ones the normal, and so the plane, is a guess).
SURFACE_DEPTHS = ("median", "planar")
NEIGHBOURS = 6  # the nearest views (by camera centre) a pixel's depth is checked against (consistency.py)
# A pixel's depth is fused when at least this many of its NEIGHBOURS nearest views see the same surface there
# (consistency.py); 0 fuses every pixel. 4 of 6 was the best of 2..5 on the generated scene and the cup
# (docs/outputs.md, "Consistent depths").
CONSISTENT_VIEWS = 4
TRUNCATION_VOXELS = 4  # half-width of the signed distance band, in voxels (the default; see docs/outputs.md)
# A view whose depth lies a band or more behind a grid point says only that the point is empty; it counts this much
# beside an observation within the band. Below 1, a surface that some views see through (semi-transparent, so their
# median depth lands behind it) is not carved away by them (docs/outputs.md, "Where MCMC's depth was lost").
FREE_WEIGHT = 1.0
# A view vouches for empty space only in front of where its ray's accumulated alpha reaches about this, not in front
# of its median depth (clear_space.py); 0.5 is the median depth itself. 0.2 and 0.07 gave the same mesh of one cup
# run (docs/outputs.md, "Views that see through a surface").
CLEAR_ALPHA = 0.2


@dataclass(frozen=True)
class MeshOptions:
    """How the mesh is made (--format mesh)."""

    voxel_size: float | None = None
    """mesh: edge of a voxel of the fusion volume, in scene units (default: the finest the budget allows)."""
    voxel_budget: int = DEFAULT_VOXEL_BUDGET
    """mesh: voxels of the fusion volume at most (memory: about 16 bytes each)."""
    alpha_min: float = 0.5
    """mesh: pixels whose accumulated alpha stays below this show no surface and fuse nothing."""
    min_component: float = 0.02
    """mesh: drop connected pieces of fewer faces than this share of the largest piece's (0 keeps all)."""
    depth: Literal["median", "planar"] = "median"
    """mesh: the depth each view fuses: median (where the ray meets the Gaussian at which alpha reaches 0.5) or
    planar (where it meets the composited plane of flat Gaussians; for runs trained with --surface)."""
    truncation: float = TRUNCATION_VOXELS
    """mesh: half-width of the signed distance band, in voxels. 16-24 suits a clean object (synthetic, or masked):
    the views' depths of a surface disagree a little, and a narrow band leaves the mesh slightly inside it; on a
    capture with floaters a wide band lets them pull the mesh outward (docs/outputs.md)."""
    consistent_views: int = CONSISTENT_VIEWS
    """mesh: fuse a pixel's depth only where at least this many of the 6 nearest training views see the same
    surface there (within 1% of its depth): floaters and stray depths are left out. 0 fuses every pixel."""
    # Not an option: benchmarks/fusion_gap.py measures it (docs/outputs.md, "Where MCMC's depth was lost").
    free_weight: Annotated[float, tyro.conf.Suppress] = FREE_WEIGHT
    # Not an option either: benchmarks/mesh_quality.py's --clear-alpha compares it with 0.5 (the median depth).
    clear_alpha: Annotated[float, tyro.conf.Suppress] = CLEAR_ALPHA

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha_min <= 1.0:
            raise MCSplatError(f"--alpha-min must be in (0, 1], got {self.alpha_min}")
        if not 1 <= self.truncation < math.inf:
            raise MCSplatError(f"--truncation must be at least 1 (voxels) and finite, got {self.truncation}")
        if self.depth not in SURFACE_DEPTHS:
            raise MCSplatError(f"--depth must be one of {', '.join(SURFACE_DEPTHS)}, got {self.depth!r}")
        if not 0 <= self.consistent_views <= NEIGHBOURS:
            raise MCSplatError(f"--consistent-views must be between 0 (fuse every pixel) and {NEIGHBOURS} (the "
                               f"nearest views a depth is checked against), got {self.consistent_views}")
        if not 0.0 < self.free_weight <= 1.0:
            raise MCSplatError(f"free_weight must be in (0, 1], got {self.free_weight}")
        if not 0.0 < self.clear_alpha <= 0.5:
            raise MCSplatError(f"clear_alpha must be in (0, 0.5], got {self.clear_alpha}")
        if not 0.0 <= self.min_component <= 1.0:
            raise MCSplatError(f"--min-component must be in [0, 1] (a share of the largest piece's faces), got "
                               f"{self.min_component}")
