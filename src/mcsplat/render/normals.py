"""Each Gaussian's normal in camera space: what render(normals=True) composites into a normal map.

A Gaussian pulled flat toward a surface element (2DGS, PGSR) has its shortest axis across the surface, so that axis
is its normal. It is turned to face the camera (a surface is seen from its front), then composited with the same
weights as the colour, over a zero background: the map holds sum_i w_i n_i, which is a unit vector only where the
pixel is opaque and its Gaussians agree. Which axis is shortest is a choice, not a function of the parameters, so
gradients reach the rotation (and, through the compositing, the weights) but not the scales.
"""

from __future__ import annotations

import torch

from ..camera import Camera
from ..geometry.rotation import quaternion_to_rotation


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
