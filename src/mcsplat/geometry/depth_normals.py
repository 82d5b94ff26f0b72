"""The normal of a depth map: what a depth-normal consistency loss holds the rendered normal map to (2DGS, PGSR).

Each pixel's depth is lifted to its camera-space point along the ray through the pixel's centre; the normal is the
cross product of the differences between the points left and right of it and above and below it, turned to face the
camera. Points of one plane give that plane's normal exactly. Where a neighbour is missing (the image's border, a
depth of 0) the pixel has no normal: zero, and False in the mask.
"""

from __future__ import annotations

import torch

from ..camera import Camera


def points_from_depth(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[H, W, 3] camera-space points of an [H, W] depth map (camera z, as render() gives it) at the pixel centres."""
    height, width = depth.shape
    K = camera.K.to(dtype=depth.dtype, device=depth.device)
    u = (torch.arange(width, dtype=depth.dtype, device=depth.device) + 0.5 - K[0, 2]) / K[0, 0]
    v = (torch.arange(height, dtype=depth.dtype, device=depth.device) + 0.5 - K[1, 2]) / K[1, 1]
    rays = torch.stack([u[None, :].expand(height, width), v[:, None].expand(height, width),
                        torch.ones(height, width, dtype=depth.dtype, device=depth.device)], dim=-1)
    return rays * depth[..., None]


def normals_from_depth(depth: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """([H, W, 3] unit camera-space normals facing the camera, [H, W] bool where there is one); differentiable in
    `depth`."""
    points = points_from_depth(depth, camera)
    across = points[1:-1, 2:] - points[1:-1, :-2]
    down = points[2:, 1:-1] - points[:-2, 1:-1]
    normal = torch.linalg.cross(across, down, dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    towards_camera = -points[1:-1, 1:-1]
    normal = torch.where((normal * towards_camera).sum(dim=-1, keepdim=True) >= 0, normal, -normal)
    seen = depth > 0
    valid = seen[1:-1, 1:-1] & seen[1:-1, 2:] & seen[1:-1, :-2] & seen[2:, 1:-1] & seen[:-2, 1:-1]
    full = torch.zeros_like(points)
    full[1:-1, 1:-1] = torch.where(valid[..., None], normal, torch.zeros_like(normal))
    mask = torch.zeros_like(seen)
    mask[1:-1, 1:-1] = valid
    return full, mask
