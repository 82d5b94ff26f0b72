"""The median depth of a pixel: the depth, along its ray, where the Gaussian at which the accumulated alpha first
reaches 0.5 (the compositing kernels find it) is densest.

In the Gaussian's own axes (rotation R, scales s) the ray t (x, y, 1), t the camera depth, becomes t rho with
rho = R^T (x, y, 1), and the mean mu = R^T m. The density exp(-1/2 sum_i (t rho_i - mu_i)^2 / s_i^2) peaks at

    t* = sum_i rho_i mu_i / s_i^2  /  sum_i rho_i^2 / s_i^2

For a flat Gaussian that is where the ray crosses its plane (2DGS's ray-splat intersection); GOF and RaDe-GS take the
same point. The centre's depth alone would put a tilted Gaussian's whole footprint at one depth, which moves a fused
surface towards the cameras by a share of the Gaussians' size. t* is kept within 3 of the Gaussian's largest scale
of its centre's depth: a ray almost along a flat Gaussian's plane would otherwise run far off.
"""

from __future__ import annotations

import torch

from ...camera import Camera
from ...geometry.rotation import quaternion_to_rotation

REACH = 3.0  # t* stays within this many of the largest scale of the centre's depth


@torch.no_grad()
def median_depth(median_ids: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                 camera: Camera) -> torch.Tensor:
    """[H, W] camera depth from the median Gaussian of each pixel ([H, W] ids, -1 where none: depth 0)."""
    hit = median_ids >= 0
    depth = torch.zeros(median_ids.shape, dtype=means.dtype, device=means.device)
    if not hit.any():
        return depth
    rows, columns = hit.nonzero(as_tuple=True)
    depth[hit] = peak_depths(median_ids[hit], pixel_rays(rows, columns, camera), means, quats, scales,
                             camera).to(means.dtype)
    return depth


def pixel_rays(rows: torch.Tensor, columns: torch.Tensor, camera: Camera) -> torch.Tensor:
    """[k, 3] float64: the rays (x, y, 1) in camera axes through the centres of pixels (rows, columns)."""
    return torch.stack([(columns.double() + 0.5 - camera.cx) / camera.fx, (rows.double() + 0.5 - camera.cy) / camera.fy,
                        torch.ones_like(rows, dtype=torch.float64)], dim=1)


@torch.no_grad()
def peak_depths(ids: torch.Tensor, rays: torch.Tensor, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                camera: Camera) -> torch.Tensor:
    """[k] float64: the camera depth t* at which Gaussian ids[i] is densest along rays[i] (camera axes, z = 1), kept
    within REACH of its largest scale of its centre's depth."""
    used, which = torch.unique(ids.long(), return_inverse=True)
    w2c = camera.world_to_camera.to(means.device, torch.float64)
    rotation = w2c[:3, :3] @ quaternion_to_rotation(quats.detach()[used].double())  # Gaussian axes -> camera
    centre = means.detach()[used].double() @ w2c[:3, :3].T + w2c[:3, 3]
    scale = scales.detach()[used].double()
    mean_local = torch.einsum("nji,nj->ni", rotation, centre)
    ray_local = torch.einsum("pji,pj->pi", rotation[which], rays.to(means.device))
    inverse_variance = scale[which].pow(-2)
    peak = (ray_local * mean_local[which] * inverse_variance).sum(1) / (ray_local.square() * inverse_variance).sum(1)
    reach = REACH * scale[which].amax(dim=1)
    centre_depth = centre[which, 2]
    return torch.minimum(torch.maximum(peak, centre_depth - reach), centre_depth + reach)
