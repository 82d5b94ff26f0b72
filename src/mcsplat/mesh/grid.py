"""The voxel grid a mesh is fused in: where it lies, how fine it is, and whether it fits in memory.

The box holds the opaque Gaussians (opacity of at least OPAQUE) that at least half of the views have in their field of
view: the object a capture goes around, not the far walls of its room, which few views face (a forward-facing capture
keeps everything, as every view sees it all). Along each axis it takes the central 98% of them, so that a few floaters
do not stretch it, and it is padded by the truncation band. The voxel size is given, or the one that fills the box
with the voxel budget. Grid point (i, j, k) sits at origin + (i, j, k) x size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from ..camera import Camera
from ..compute.device import free_memory
from ..errors import MCSplatError
from ..render.constants import NEAR_PLANE
from .options import TRUNCATION_VOXELS

OPAQUE = 0.1           # Gaussians at least this opaque decide the box
IN_VIEW_SHARE = 0.5    # ... when at least this share of the views has them in its field of view
BOX_QUANTILE = 0.01    # ... the box holds all but this share of them on each side, along each axis
# Per voxel: signed distance and weight (float32), colour (3 x float16), two masks when meshing (bool).
BYTES_PER_VOXEL = 4 + 4 + 3 * 2 + 2
MEMORY_SHARE = 0.8     # of the free memory the volume may take (the rest: renders, marching cubes, the mesh)
MIN_VOXELS_PER_SIDE = 8


@dataclass(frozen=True)
class VoxelGrid:
    origin: tuple[float, float, float]  # world position of grid point (0, 0, 0)
    voxel_size: float
    shape: tuple[int, int, int]
    truncation_voxels: float = TRUNCATION_VOXELS  # half-width of the signed distance band

    @property
    def num_voxels(self) -> int:
        return math.prod(self.shape)

    @property
    def truncation(self) -> float:
        """Half-width of the signed distance band, in world units."""
        return self.truncation_voxels * self.voxel_size

    def to_world(self, points: torch.Tensor) -> torch.Tensor:
        """[..., 3] grid coordinates (voxel units, fractional) -> world coordinates."""
        origin = torch.tensor(self.origin, dtype=points.dtype, device=points.device)
        return origin + points * self.voxel_size

    def describe(self) -> str:
        nx, ny, nz = self.shape
        return f"{nx}x{ny}x{nz} voxels of {self.voxel_size:.4g}"


def object_box(means: torch.Tensor, opacities: torch.Tensor, cameras: Sequence[Camera]
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """(lowest, highest) corner [3] of the box that holds the opaque Gaussians most views see (module docstring)."""
    opaque = means[opacities >= OPAQUE].detach().float()
    if opaque.shape[0] < 2:
        raise MCSplatError(f"the model has {opaque.shape[0]} Gaussian(s) of opacity {OPAQUE} or more: nothing to "
                           f"mesh; train the run further")
    in_view = sum(_in_field_of_view(opaque, camera).float() for camera in cameras) / len(cameras)
    if int((in_view >= IN_VIEW_SHARE).sum()) >= 2:
        opaque = opaque[in_view >= IN_VIEW_SHARE]
    if opaque.shape[0] > 1_000_000:  # torch.quantile's limit is 2^24 elements; a sample finds the box as well
        opaque = opaque[torch.randperm(opaque.shape[0], generator=torch.Generator().manual_seed(0))[:1_000_000]
                        .to(opaque.device)]
    bounds = torch.quantile(opaque, torch.tensor([BOX_QUANTILE, 1 - BOX_QUANTILE], device=opaque.device), dim=0)
    return bounds[0], bounds[1]


def _in_field_of_view(points: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[N] bool: in front of the camera and projected inside its image."""
    return camera.pixels_of(camera.to_camera_space(points), near=NEAR_PLANE)[2]


def choose_grid(low: torch.Tensor, high: torch.Tensor, voxel_size: float | None, voxel_budget: int,
                truncation_voxels: float = TRUNCATION_VOXELS) -> VoxelGrid:
    """The grid over the box [low, high] widened by TRUNCATION_VOXELS + 1 voxels: voxels of `voxel_size`, or the
    finest that keeps to `voxel_budget` voxels, with a band of `truncation_voxels` (one wider than the margin is
    cut off at the grid's edge, so that the grid does not depend on it)."""
    if voxel_budget < MIN_VOXELS_PER_SIDE ** 3:
        raise MCSplatError(f"--voxel-budget {voxel_budget:,} is too small; give at least {MIN_VOXELS_PER_SIDE ** 3:,}")
    if voxel_size is not None and not 0 < voxel_size < math.inf:
        raise MCSplatError(f"--voxel-size must be a positive finite number, got {voxel_size}")
    extent = (high - low).double().clamp(min=1e-9).tolist()
    size = voxel_size if voxel_size is not None else _finest_size(extent, voxel_budget)
    margin = (TRUNCATION_VOXELS + 1) * size
    grid = VoxelGrid(origin=tuple(float(v) - margin for v in low.tolist()), voxel_size=float(size),  # type: ignore
                     shape=_shape(extent, size), truncation_voxels=truncation_voxels)
    if grid.num_voxels > voxel_budget:
        raise MCSplatError(f"--voxel-size {size:.4g} needs {grid.describe()} = {grid.num_voxels:,} voxels, over the "
                           f"budget of {voxel_budget:,}; raise --voxel-size or --voxel-budget")
    return grid


def _shape(extent: list[float], size: float) -> tuple[int, int, int]:
    """Grid points along each axis: the extent and a margin of the band plus one voxel on both ends."""
    return tuple(math.ceil(e / size) + 2 * (TRUNCATION_VOXELS + 1) + 1 for e in extent)  # type: ignore[return-value]


def _finest_size(extent: list[float], budget: int) -> float:
    """The smallest voxel size whose grid keeps to `budget` (bisection: the count only falls as the size grows)."""
    low, high = max(extent) * 1e-6, max(extent)
    while math.prod(_shape(extent, high)) > budget:  # a budget near the minimum: the margins alone fill it
        high *= 2
    for _ in range(60):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if math.prod(_shape(extent, middle)) > budget else (low, middle)
    return high


def check_memory(grid: VoxelGrid, device: torch.device) -> None:
    """A one-line error, before anything is allocated, when the volume would not fit in free memory."""
    need = grid.num_voxels * BYTES_PER_VOXEL
    free = free_memory(device)
    if free is not None and need > MEMORY_SHARE * free:
        raise MCSplatError(f"the volume of {grid.describe()} needs {need / 2**30:.1f} GiB, more than "
                           f"{MEMORY_SHARE:.0%} of the {free / 2**30:.1f} GiB free on {device}; lower --voxel-budget "
                           f"(or raise --voxel-size)")
