"""Each Gaussian's normal in camera space: what render(outputs={"normals"}) composites into a normal map.

A Gaussian pulled flat toward a surface element (2DGS, PGSR) has its shortest axis across the surface, so that axis
is its normal. It is turned to face the camera (a surface is seen from its front), then composited with the same
weights as the colour, over a zero background: the map holds sum_i w_i n_i, which is a unit vector only where the
pixel is opaque and its Gaussians agree. Which axis is shortest is a choice, not a function of the parameters: the
normal passes its gradient to the rotation only (the scales get theirs through the compositing weights).

The planar depth (PGSR's unbiased depth) goes with it: each Gaussian's plane is {x : n . x = d} with d = n . mean,
the plane distances are composited like the normals, and each pixel's depth is where its ray meets the plane of the
composited normal and distance, d / (n . ray). A flat Gaussian seen at a slant then gives the depth of the surface
it lies on at every pixel it covers, where the expected depth gives its centre's depth to all of them; the normal of
that depth map is what a depth-normal consistency loss holds the normal map to (geometry/depth_normals.py).
"""

from __future__ import annotations

import torch

from ...camera import Camera
from ...geometry.depth_normals import points_from_depth
from ...geometry.rotation import quaternion_to_rotation

MIN_SLANT = 1e-3  # |n . ray| below this (a plane seen edge-on, or no Gaussian): no planar depth


def gaussian_normals(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[N, 3] unit normals in camera space (x right, y down, z forward), each facing the camera."""
    rotation = quaternion_to_rotation(quats)  # the Gaussian's axes are its columns (covariance R S S^T R^T)
    shortest = scales.detach().argmin(dim=-1)
    axis = torch.take_along_dim(rotation, shortest[:, None, None].expand(-1, 3, 1), dim=2)[..., 0]
    world_to_camera = camera.world_to_camera.to(dtype=means.dtype, device=means.device)
    turn, shift = world_to_camera[:3, :3], world_to_camera[:3, 3]
    normal = axis @ turn.T
    towards_camera = -(means @ turn.T + shift)  # from the Gaussian to the camera's centre, in camera space
    facing = (normal * towards_camera).sum(dim=-1, keepdim=True) >= 0
    return torch.where(facing, normal, -normal)


def plane_distances(normals: torch.Tensor, means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[N] d = n . mean in camera space (negative: the normals face the camera) for each Gaussian's plane."""
    world_to_camera = camera.world_to_camera.to(dtype=means.dtype, device=means.device)
    return (normals * (means @ world_to_camera[:3, :3].T + world_to_camera[:3, 3])).sum(dim=-1)


def depth_from_planes(normal_map: torch.Tensor, distance_map: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[H, W] camera depth where each pixel's ray meets the plane n . x = d of its composited normal and distance;
    0 where the plane is seen edge-on or absent (|n . ray| < MIN_SLANT)."""
    rays = points_from_depth(torch.ones_like(distance_map), camera)  # the pixel centres' rays at depth 1
    slant = (normal_map * rays).sum(dim=-1)
    usable = slant.abs() >= MIN_SLANT
    depth = distance_map / torch.where(usable, slant, torch.ones_like(slant))
    return torch.where(usable & (depth > 0), depth, torch.zeros_like(depth))
