"""Two views' depth maps against each other: each pixel of one view sent to the other by its depth, and back by the
other's depth where it landed (PGSR's multi-view geometric consistency, with depths in place of its homographies:
the same points where the depth is that of the pixel's plane; the other's depth is interpolated as inverse depth,
which is exact on a plane).

Where both depth maps hold the same surface, a pixel comes back to where it started; the distance it comes back at,
in pixels of the first view, measures how far they disagree. A pixel that lands outside the other view's pixel
centres, behind its camera or where it has no depth has no error (False in the mask). An occluded one comes back
far: the loss term leaves those out by a threshold.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..camera import Camera
from .depth_normals import points_from_depth

NEAR = 1e-6  # camera depth a point must exceed to project


def _to_world(points: torch.Tensor, camera: Camera) -> torch.Tensor:
    w2c = camera.world_to_camera.to(points.device, points.dtype)
    return (points - w2c[:3, 3]) @ w2c[:3, :3]  # R^T (p - t), row vectors


def _project(world: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(u, v, z) of world points [..., 3] in `camera` (pixel centres at +0.5; z the camera depth, kept above NEAR
    for the division)."""
    w2c = camera.world_to_camera.to(world.device, world.dtype)
    K = camera.K.to(world.device, world.dtype)
    local = world @ w2c[:3, :3].T + w2c[:3, 3]
    z = local[..., 2]
    z_safe = z.clamp_min(NEAR)
    return local[..., 0] / z_safe * K[0, 0] + K[0, 2], local[..., 1] / z_safe * K[1, 1] + K[1, 2], z


def _sample(image: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an [H, W] map at pixel coordinates (centres at +0.5), differentiable in both."""
    height, width = image.shape
    grid = torch.stack([2.0 * u / width - 1.0, 2.0 * v / height - 1.0], dim=-1)[None]
    return F.grid_sample(image[None, None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0]


def round_trip_error(depth: torch.Tensor, camera: Camera, other_depth: torch.Tensor,
                     other: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """([H, W] the distance in pixels at which each pixel of `depth` (seen by `camera`) comes back after a trip to
    `other` and back by `other_depth`, [H, W] bool where the trip was made); differentiable in both depth maps."""
    height, width = depth.shape
    world = _to_world(points_from_depth(depth, camera), camera)
    u, v, z = _project(world, other)
    other_height, other_width = other_depth.shape
    # between the other's pixel centres, where its depth is interpolated, not held at its border
    landed = (depth > 0) & (z > NEAR) & (u >= 0.5) & (u <= other_width - 0.5) & (v >= 0.5) & (v <= other_height - 0.5)
    # Inverse depth is affine in the pixel coordinates on a plane: interpolated, it gives the plane's depth exactly
    has_depth = other_depth > 0
    inverse = torch.where(has_depth, 1.0 / torch.where(has_depth, other_depth, torch.ones_like(other_depth)), 0.0)
    whole = _sample(has_depth.to(depth.dtype), u, v) > 0.999  # not mixed with a pixel without depth
    there = 1.0 / torch.where(whole, _sample(inverse, u, v), torch.ones_like(u))
    K = other.K.to(depth.device, depth.dtype)
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)
    back_u, back_v, back_z = _project(_to_world(rays * there[..., None], other), camera)
    x = torch.arange(width, dtype=depth.dtype, device=depth.device) + 0.5
    y = torch.arange(height, dtype=depth.dtype, device=depth.device) + 0.5
    error = torch.sqrt((back_u - x[None, :]) ** 2 + (back_v - y[:, None]) ** 2 + 1e-12)
    valid = landed & whole & (back_z > NEAR)
    return torch.where(valid, error, torch.zeros_like(error)), valid


def neighbours(cameras: list[Camera], count: int = 8, max_angle: float = 30.0,
               min_distance: float = 0.0) -> list[list[int]]:
    """For each camera, the indices of up to `count` others nearest to it by centre, among those looking within
    `max_angle` degrees of its direction and farther than `min_distance` (a second view of the same surface from
    another place, as PGSR picks them)."""
    centres = torch.stack([camera.center.detach().to("cpu", torch.float64) for camera in cameras])
    axes = torch.stack([camera.world_to_camera.detach().to("cpu", torch.float64)[2, :3] for camera in cameras])
    distance = torch.cdist(centres, centres)
    aligned = (axes @ axes.T) >= torch.cos(torch.deg2rad(torch.tensor(max_angle, dtype=torch.float64)))
    found = []
    for index in range(len(cameras)):
        allowed = aligned[index] & (distance[index] > min_distance)
        allowed[index] = False
        order = [int(k) for k in torch.argsort(distance[index]) if allowed[k]]
        found.append(order[:count])
    return found
