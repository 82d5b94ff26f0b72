"""Multi-view consistency of the views' depth maps: a pixel's depth is fused only where enough of the nearest other
views see the same surface there.

Each pixel's depth is lifted to its world point and projected into the NEIGHBOURS views whose centres are nearest;
a neighbour agrees when its own depth at that pixel is within `tolerance` (relative) of the point's depth in it. A
pixel with fewer than `need` agreeing neighbours is left out of the fusion. This is the geometric consistency check
multi-view stereo pipelines run before they fuse depth maps. Here it removes what one view's median depth places
and the others do not confirm: a floater a few views see in front of the surface, a depth straddling an outline, a
surface only half converged. Those are also what pulled a narrow band inward (docs/outputs.md, "Consistent depths").

The neighbours' depths are kept in float16 (its 0.05% relative step is far below the tolerance) at a stride that
keeps their long side at most CHECK_SIZE pixels, so that a capture of hundreds of 4K views needs a few hundred MB.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from ..camera import Camera
from ..geometry.depth_normals import points_from_depth
from .options import NEIGHBOURS

TOLERANCE = 0.01     # relative depth difference within which a neighbour agrees
CHECK_SIZE = 1024    # long side, in pixels, of the kept depth maps at most


def nearest_views(cameras: Sequence[Camera], count: int = NEIGHBOURS) -> list[list[int]]:
    """For each camera, the indices of the `count` others whose centres are nearest (all others when fewer)."""
    centres = torch.stack([camera.center.double().cpu() for camera in cameras])
    distances = torch.cdist(centres, centres)
    distances.fill_diagonal_(float("inf"))
    count = min(count, len(cameras) - 1)
    return [row.argsort()[:count].tolist() for row in distances]


class KeptDepth:
    """One view's depth map at a stride: what the other views check their pixels against."""

    def __init__(self, camera: Camera, depth: torch.Tensor):
        self.stride = max(1, math.ceil(max(depth.shape) / CHECK_SIZE))
        half = self.stride // 2
        self.depth = depth[half::self.stride, half::self.stride].to(torch.float16)
        self.camera = camera

    def agrees(self, points: torch.Tensor, tolerance: float) -> torch.Tensor:
        """[N] bool: world points [N, 3] that this view sees at their own depth, within `tolerance` of it."""
        local = self.camera.to_camera_space(points)
        z = local[:, 2]
        column, row, inside = self.camera.pixels_of(local)
        height, width = self.depth.shape
        kept_row = (row / self.stride).long().clamp_(0, height - 1)
        kept_column = (column / self.stride).long().clamp_(0, width - 1)
        seen = self.depth[kept_row, kept_column].float()  # -inf where the view sees no surface: never agrees
        return inside & ((seen - z).abs() <= tolerance * z)


def consistent_depth(depth: torch.Tensor, camera: Camera, neighbours: Sequence[KeptDepth], need: int,
                     tolerance: float = TOLERANCE) -> torch.Tensor:
    """`depth` [H, W] (-inf where no surface) with -inf also where fewer than `need` of `neighbours` agree."""
    seen = torch.isfinite(depth)
    if need <= 0 or not seen.any():
        return depth
    local = points_from_depth(torch.where(seen, depth, torch.zeros_like(depth)), camera)[seen]
    camera_to_world = torch.linalg.inv(camera.world_to_camera.to(depth.device, torch.float64)).float()
    points = local @ camera_to_world[:3, :3].T + camera_to_world[:3, 3]
    votes = torch.zeros(points.shape[0], dtype=torch.int32, device=depth.device)
    for neighbour in neighbours:
        votes += neighbour.agrees(points, tolerance)
    kept = torch.full_like(depth, -float("inf"))
    kept[seen] = torch.where(votes >= need, depth[seen], kept[seen])
    return kept
