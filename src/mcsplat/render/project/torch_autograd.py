"""EWA projection of 3D Gaussians to the image plane, in torch so that autograd gives the backward.

Conventions: OpenCV camera (x right, y down, z forward), pixel centres at +0.5 (COLMAP). The 2D covariance gets the
3DGS low-pass filter (+0.3 px on the diagonal; with `antialiased`, Mip-Splatting's 2D filter: the same low-pass and
the opacity scaled by the ratio of the splat's areas before and after it, as gsplat's antialiased mode); the Jacobian
uses the view direction clamped to 1.3x the field of view (as 3DGS and gsplat do) so that Gaussians far outside the
image do not blow up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ...camera import Camera
from ...geometry.rotation import covariance_3d
from ...geometry.sh import eval_sh
from ..constants import FAR_PLANE, LOW_PASS, NEAR_PLANE, TILE_SIZE


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities. Culled Gaussians have radius 0 and an empty tile rectangle."""

    means2d: torch.Tensor   # [N, 2] pixels
    conics: torch.Tensor    # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    depths: torch.Tensor    # [N] camera-space z
    radii: torch.Tensor     # [N] int32 pixels, 0 where culled
    tile_min: torch.Tensor  # [N, 2] int32 (x, y), inclusive
    tile_max: torch.Tensor  # [N, 2] int32 (x, y), exclusive
    alpha_extent: torch.Tensor  # [N, 2] half-size in pixels of the box outside which alpha < 1/255 (0: never)
    # [N] antialiased only: sqrt(det before / det after the low-pass), the factor the opacity is drawn with; radii,
    # tiles and alpha extents come from the uncompensated opacity (a little wider than needed, never too narrow).
    compensations: torch.Tensor | None = None


def project_gaussians(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      camera: Camera, *, near: float = NEAR_PLANE, far: float = FAR_PLANE,
                      eps2d: float = LOW_PASS, opacity_aware_radius: bool = False,
                      antialiased: bool = False) -> Projection:
    dtype, device = means.dtype, means.device
    w2c = camera.world_to_camera.to(device=device, dtype=dtype)
    rotation, translation = w2c[:3, :3], w2c[:3, 3]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    width, height = camera.width, camera.height

    p_cam = means @ rotation.T + translation
    z = p_cam[:, 2]
    in_range = (z > near) & (z < far)
    # Culled Gaussians still flow through the maths: a safe depth keeps their (unused) gradients finite.
    z_safe = torch.where(in_range, z, torch.ones_like(z))
    x, y = p_cam[:, 0], p_cam[:, 1]

    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.clamp(x / z_safe, -lim_x_neg, lim_x_pos)
    ty = z_safe * torch.clamp(y / z_safe, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(z_safe)
    jacobian = torch.stack([
        fx / z_safe, zero, -fx * tx / (z_safe * z_safe),
        zero, fy / z_safe, -fy * ty / (z_safe * z_safe),
    ], dim=-1).reshape(-1, 2, 3)

    cov_world = covariance_3d(quats, scales)
    cov_cam = rotation @ cov_world @ rotation.T
    cov2d = jacobian @ cov_cam @ jacobian.transpose(1, 2)
    a = cov2d[:, 0, 0] + eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    valid = in_range & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)
    compensations = None
    if antialiased:
        ratio = (cov2d[:, 0, 0] * cov2d[:, 1, 1] - b * b) / det_safe
        positive = ratio > 0
        compensations = torch.where(positive, torch.sqrt(torch.where(positive, ratio, 1.0)), 0.0)

    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    with torch.no_grad():
        radii, tile_min, tile_max = _screen_extent(means2d, a, b, c, opacities, valid, width, height,
                                                   opacity_aware_radius)
        alpha_extent = _alpha_extent(a, c, opacities)
    return Projection(means2d=means2d, conics=conics, depths=z, radii=radii, tile_min=tile_min, tile_max=tile_max,
                      alpha_extent=alpha_extent, compensations=compensations)


def _alpha_extent(a: torch.Tensor, c: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """Half-widths of the axis-aligned box around the ellipse where o exp(-d^T Q d / 2) >= 1/255.

    The ellipse d^T Sigma^-1 d <= k has |dx| <= sqrt(k Sigma_xx) and |dy| <= sqrt(k Sigma_yy), k = 2 ln(255 o).
    Outside the box the compositing test alpha >= 1/255 fails, so the rasterizer may skip those pixels unseen; the
    small relative and absolute margins cover rounding in the conic.
    """
    k = torch.clamp(2.0 * torch.log(torch.clamp(255.0 * opacities.detach(), min=1e-30)), min=0.0)
    extent = torch.sqrt(k[:, None] * torch.stack([a, c], dim=-1).clamp(min=0.0))
    return torch.where(k[:, None] > 0, extent * 1.001 + 0.01, torch.zeros_like(extent))


def _screen_extent(means2d, a, b, c, opacities, valid, width, height, opacity_aware_radius):
    """Pixel radius from the largest eigenvalue and the tiles it touches; culls whatever touches no tile."""
    mid = 0.5 * (a + c)
    lambda_max = mid + torch.sqrt(torch.clamp(0.25 * (a - c) ** 2 + b * b, min=0.1))
    extent = torch.full_like(a, 3.0)
    if opacity_aware_radius:
        # Beyond sqrt(2 ln(255 o)) sigma the alpha falls under 1/255 and the pixel is skipped anyway.
        extent = torch.sqrt(torch.clamp(2.0 * torch.log(torch.clamp(255.0 * opacities, min=1.0)), min=0.0))
        extent = torch.clamp(extent, max=3.0)
        valid = valid & (255.0 * opacities > 1.0)
    radius = torch.ceil(extent * torch.sqrt(torch.clamp(lambda_max, min=0.0)))
    tiles_x, tiles_y = math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)
    limits = torch.tensor([tiles_x, tiles_y], device=means2d.device)
    lo = torch.floor((means2d - radius[:, None]) / TILE_SIZE)
    hi = torch.floor((means2d + radius[:, None]) / TILE_SIZE) + 1
    # Clamp in floating point first: a far-off Gaussian's pixel coordinate can exceed the int32 range.
    tile_min = torch.minimum(torch.clamp(lo, min=0), limits).to(torch.int32)
    tile_max = torch.minimum(torch.clamp(hi, min=0), limits).to(torch.int32)
    valid = valid & (radius > 0) & (tile_max > tile_min).all(dim=-1) & torch.isfinite(means2d).all(dim=-1)
    radii = torch.where(valid, radius, torch.zeros_like(radius)).to(torch.int32)
    tile_min = torch.where(valid[:, None], tile_min, torch.zeros_like(tile_min))
    tile_max = torch.where(valid[:, None], tile_max, torch.zeros_like(tile_max))
    return radii, tile_min, tile_max


def view_dependent_colors(means: torch.Tensor, sh: torch.Tensor, camera: Camera, sh_degree: int) -> torch.Tensor:
    """RGB per Gaussian from SH along the camera-to-Gaussian direction, +0.5 and clamped at 0 (as in 3DGS)."""
    center = camera.center.to(device=means.device, dtype=means.dtype)
    dirs = torch.nn.functional.normalize(means - center, dim=-1)
    return torch.clamp_min(eval_sh(sh_degree, sh, dirs) + 0.5, 0.0)


def project_and_shade_torch(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                            sh: torch.Tensor, camera: Camera, sh_degree: int, *, sh_rest: torch.Tensor | None = None,
                            **options) -> tuple[Projection, torch.Tensor]:
    """The projection stage in torch, with warp_kernel.project_and_shade's signature (the baseline render path)."""
    if sh_rest is not None:
        sh = torch.cat([sh, sh_rest], dim=1)
    return (project_gaussians(means, quats, scales, opacities, camera, **options),
            view_dependent_colors(means, sh, camera, sh_degree))
