"""A dense, obviously-correct pure-PyTorch renderer: the test oracle for the Warp rasterizer. Never used to train.

Every pixel looks at every Gaussian (an [H*W, N] matrix), so it needs O(H W N) memory: keep scenes tiny. It follows
the same rules as the fast path: EWA projection with the 0.3 px low-pass, 3-sigma (or opacity-aware) radius and 16x16
tile rectangles (a Gaussian only reaches pixels of the tiles its rectangle covers), alpha = min(0.99, o G) (o times
sqrt(det Sigma2D / det(Sigma2D + 0.3 I)) when antialiased, the tiles still from o alone), skip
alpha < 1/255, stop before transmittance falls below 1e-4. Gradients come from autograd alone. The median Gaussian
of a pixel is the last one composited while the transmittance in front of it is above 0.5; the median depth is where
the pixel's ray meets its density's peak (render/outputs/median.py), here through the inverse of the 3D covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..camera import Camera
from ..geometry.rotation import covariance_3d
from ..geometry.sh import eval_sh
from .constants import (ALPHA_MAX, ALPHA_MIN, LOW_PASS, MEDIAN_TRANSMITTANCE, NEAR_PLANE, TILE_SIZE,
                        TRANSMITTANCE_MIN)


@dataclass
class ReferenceResult:
    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor      # expected depth
    median_ids: torch.Tensor    # [H, W] the median Gaussian, -1 where none
    median_depth: torch.Tensor  # [H, W] no gradient
    means2d: torch.Tensor    # kept in the graph with retain_grad()
    radii: torch.Tensor


def reference_render(gaussians, camera: Camera, background=None, sh_degree: int | None = None, *,
                     near: float = NEAR_PLANE, eps2d: float = LOW_PASS, opacity_aware_radius: bool = False,
                     antialiased: bool = False) -> ReferenceResult:
    means, quats, scales = gaussians.means, gaussians.quats, gaussians.scales
    opacities, sh = gaussians.opacities, gaussians.sh
    dtype, device = means.dtype, means.device
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else \
        torch.as_tensor(background, dtype=dtype, device=device).reshape(3)
    degree = round(math.sqrt(sh.shape[1])) - 1 if sh_degree is None else sh_degree

    means2d, conics, depths, radii, tile_min, tile_max, compensations = reference_project(
        means, quats, scales, opacities, camera, near=near, eps2d=eps2d, opacity_aware_radius=opacity_aware_radius)
    if antialiased:
        opacities = opacities * compensations
    means2d.retain_grad() if means2d.requires_grad else None
    cam_center = -camera.world_to_camera[:3, :3].T.to(dtype) @ camera.world_to_camera[:3, 3].to(dtype)
    dirs = (means - cam_center) / torch.linalg.norm(means - cam_center, dim=-1, keepdim=True)
    colors = torch.clamp(eval_sh(degree, sh, dirs) + 0.5, min=0.0)
    rgb, alpha, depth_sum = reference_composite(means2d, conics, opacities, colors, depths, radii, tile_min,
                                                tile_max, bg, camera.width, camera.height)
    depth = torch.where(alpha > 0, depth_sum / torch.clamp(alpha, min=1e-10), torch.zeros_like(depth_sum))
    median_ids = reference_median_gaussian(means2d, conics, opacities, depths, radii, tile_min, tile_max,
                                           camera.width, camera.height)
    median = reference_median_depth(median_ids, means, quats, scales, camera)
    return ReferenceResult(rgb=rgb, alpha=alpha, depth=depth, median_ids=median_ids, median_depth=median,
                           means2d=means2d, radii=radii)


def reference_project(means, quats, scales, opacities, camera: Camera, *, near=NEAR_PLANE, eps2d=LOW_PASS,
                      opacity_aware_radius=False):
    """Per-Gaussian 2D mean, conic, depth, pixel radius, tile rectangle and antialiasing compensation (the square
    root of the ratio of the 2D covariance's determinant without and with the low-pass), matrix by matrix."""
    dtype, device = means.dtype, means.device
    w2c = camera.world_to_camera.to(device, dtype)
    K = camera.K.to(device, dtype)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W, H = camera.width, camera.height
    out_means2d, out_conics, out_depths, out_radii, out_min, out_max, out_comp = [], [], [], [], [], [], []
    for i in range(means.shape[0]):
        p = w2c[:3, :3] @ means[i] + w2c[:3, 3]
        x, y, z = p[0], p[1], p[2]
        q = quats[i] / torch.linalg.norm(quats[i])
        w, qx, qy, qz = q[0], q[1], q[2], q[3]
        rot = torch.stack([
            torch.stack([1 - 2 * (qy ** 2 + qz ** 2), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)]),
            torch.stack([2 * (qx * qy + w * qz), 1 - 2 * (qx ** 2 + qz ** 2), 2 * (qy * qz - w * qx)]),
            torch.stack([2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx ** 2 + qy ** 2)]),
        ])
        sigma = rot @ torch.diag(scales[i] ** 2) @ rot.T
        visible = bool(z > near)
        zs = z if visible else torch.ones((), dtype=dtype, device=device)
        # View direction clamped to 1.3x the field of view for the Jacobian only.
        tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
        u = torch.clamp(x / zs, -(cx / fx + 0.3 * tan_x), (W - cx) / fx + 0.3 * tan_x) * zs
        v = torch.clamp(y / zs, -(cy / fy + 0.3 * tan_y), (H - cy) / fy + 0.3 * tan_y) * zs
        zero = torch.zeros((), dtype=dtype, device=device)
        J = torch.stack([torch.stack([fx / zs, zero, -fx * u / zs ** 2]),
                         torch.stack([zero, fy / zs, -fy * v / zs ** 2])])
        unfiltered = J @ w2c[:3, :3] @ sigma @ w2c[:3, :3].T @ J.T
        cov2d = unfiltered + eps2d * torch.eye(2, dtype=dtype, device=device)
        det = torch.linalg.det(cov2d)
        visible = visible and bool(det > 0)
        ratio = torch.linalg.det(unfiltered) / det if visible else torch.zeros((), dtype=dtype, device=device)
        out_comp.append(torch.sqrt(ratio) if bool(ratio > 0) else torch.zeros((), dtype=dtype, device=device))
        inv = torch.linalg.inv(cov2d) if visible else torch.eye(2, dtype=dtype, device=device)
        mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy])

        radius, lo, hi = 0, (0, 0), (0, 0)
        if visible:
            k = 3.0
            if opacity_aware_radius:
                o = float(opacities[i].detach())
                k = min(3.0, math.sqrt(2.0 * math.log(255.0 * o))) if 255.0 * o > 1.0 else 0.0
            # Same floor of 0.1 under the square root as 3DGS, so the radius matches for near-isotropic splats.
            a, b, c = (float(v) for v in cov2d.detach()[[0, 0, 1], [0, 1, 1]])
            lam = 0.5 * (a + c) + math.sqrt(max(0.1, 0.25 * (a - c) ** 2 + b * b))
            radius = math.ceil(k * math.sqrt(lam))
            mx, my = (float(v) for v in mean2d.detach())
            tiles = (math.ceil(W / TILE_SIZE), math.ceil(H / TILE_SIZE))
            lo = tuple(min(max(math.floor((m - radius) / TILE_SIZE), 0), t) for m, t in zip((mx, my), tiles))
            hi = tuple(min(max(math.floor((m + radius) / TILE_SIZE) + 1, 0), t) for m, t in zip((mx, my), tiles))
            if radius == 0 or hi[0] <= lo[0] or hi[1] <= lo[1]:
                radius, lo, hi = 0, (0, 0), (0, 0)
        out_means2d.append(mean2d)
        out_conics.append(torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]))
        out_depths.append(z)
        out_radii.append(radius)
        out_min.append(lo)
        out_max.append(hi)
    n = means.shape[0]
    ints = dict(dtype=torch.int32, device=device)
    if n == 0:
        empty = means.new_zeros(0, 2)
        return (empty, means.new_zeros(0, 3), means.new_zeros(0), torch.zeros(0, **ints),
                torch.zeros(0, 2, **ints), torch.zeros(0, 2, **ints), means.new_zeros(0))
    return (torch.stack(out_means2d), torch.stack(out_conics), torch.stack(out_depths),
            torch.tensor(out_radii, **ints), torch.tensor(out_min, **ints), torch.tensor(out_max, **ints),
            torch.stack(out_comp))


def _front_to_back(means2d, conics, opacities, depths, radii, tile_min, tile_max, width: int, height: int):
    """Every pixel against every visible Gaussian, front to back -> (visible Gaussians in depth order [N'], alpha
    [P, N'] (0 where not used), included [P, N'] (before the pixel's early stop), transmittance in front [P, N'])."""
    dtype, device = means2d.dtype, means2d.device
    ys, xs = torch.meshgrid(torch.arange(height, device=device), torch.arange(width, device=device), indexing="ij")
    px, py = xs.reshape(-1), ys.reshape(-1)
    keep = torch.nonzero(radii > 0).squeeze(1)
    # Front to back; equal depths keep index order, as the fast path does.
    keep = keep[torch.argsort(depths.detach()[keep], stable=True)]
    m, q = means2d[keep], conics[keep]
    dx = m[None, :, 0] - (px[:, None].to(dtype) + 0.5)   # [P, N]
    dy = m[None, :, 1] - (py[:, None].to(dtype) + 0.5)
    power = -0.5 * (q[None, :, 0] * dx ** 2 + q[None, :, 2] * dy ** 2) - q[None, :, 1] * dx * dy
    alpha = torch.clamp(opacities[keep][None, :] * torch.exp(power), max=ALPHA_MAX)
    tx, ty = (px // TILE_SIZE)[:, None], (py // TILE_SIZE)[:, None]
    in_rect = ((tx >= tile_min[keep, 0][None]) & (tx < tile_max[keep, 0][None])
               & (ty >= tile_min[keep, 1][None]) & (ty < tile_max[keep, 1][None]))
    used = in_rect & (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    # Early stop: a Gaussian counts only while the transmittance after it stays >= 1e-4. That test is monotone
    # along the list, so "included" is a prefix of the used Gaussians of each pixel.
    with torch.no_grad():
        t_after = torch.cumprod(1.0 - alpha, dim=1)
        included = t_after >= TRANSMITTANCE_MIN
    factors = torch.where(included, 1.0 - alpha, torch.ones_like(alpha))
    t_before = torch.cat([torch.ones_like(factors[:, :1]), torch.cumprod(factors, dim=1)[:, :-1]], dim=1)
    return keep, alpha, included, t_before


def reference_composite(means2d, conics, opacities, colors, depths, radii, tile_min, tile_max, background,
                        width: int, height: int):
    """Dense front-to-back compositing -> (rgb [H,W,3], alpha [H,W], alpha-weighted depth sum [H,W])."""
    dtype, device = means2d.dtype, means2d.device
    if not (radii > 0).any():
        rgb = background.reshape(1, 1, 3).expand(height, width, 3).clone()
        zeros = torch.zeros(height, width, dtype=dtype, device=device)
        return rgb + 0 * means2d.sum(), zeros, zeros.clone()
    keep, alpha, included, t_before = _front_to_back(means2d, conics, opacities, depths, radii, tile_min, tile_max,
                                                     width, height)
    weights = torch.where(included, alpha * t_before, torch.zeros_like(alpha))
    t_final = torch.where(included, 1.0 - alpha, torch.ones_like(alpha)).prod(dim=1)
    rgb = weights @ colors[keep] + t_final[:, None] * background[None, :]
    depth = weights @ depths[keep]
    return rgb.reshape(height, width, 3), (1.0 - t_final).reshape(height, width), depth.reshape(height, width)


def reference_distortion(means2d, conics, opacities, inverse_depths, depths, radii, tile_min, tile_max, width: int,
                         height: int):
    """[H, W] 2DGS's depth distortion as its definition reads, every ordered pair of a pixel's Gaussians:
    sum_{j<i} w_i w_j (m_i - m_j)^2 with m the given inverse depths (an [H W, N, N] tensor: keep scenes tiny)."""
    if not (radii > 0).any():
        return torch.zeros(height, width, dtype=means2d.dtype, device=means2d.device) + 0 * means2d.sum()
    keep, alpha, included, t_before = _front_to_back(means2d, conics, opacities, depths, radii, tile_min, tile_max,
                                                     width, height)
    weights = torch.where(included, alpha * t_before, torch.zeros_like(alpha))
    m = inverse_depths[keep]
    gaps = (m[:, None] - m[None, :]) ** 2                      # [N', N'], (i, j)
    in_front = torch.ones_like(gaps, dtype=torch.bool).tril(diagonal=-1)  # j < i
    pairs = weights[:, :, None] * weights[:, None, :] * torch.where(in_front, gaps, torch.zeros_like(gaps))[None]
    return pairs.sum(dim=(1, 2)).reshape(height, width)


@torch.no_grad()
def reference_median_gaussian(means2d, conics, opacities, depths, radii, tile_min, tile_max, width: int, height: int):
    """[H, W] int64: the last Gaussian a pixel composites while its transmittance is still above 0.5 (where the
    accumulated alpha first reaches 0.5, or the last one where it never does); -1 where none is composited."""
    if not (radii > 0).any():
        return torch.full((height, width), -1, dtype=torch.int64, device=means2d.device)
    keep, alpha, included, t_before = _front_to_back(means2d, conics, opacities, depths, radii, tile_min, tile_max,
                                                     width, height)
    candidate = included & (alpha > 0) & (t_before > MEDIAN_TRANSMITTANCE)
    order = torch.arange(1, keep.numel() + 1, device=means2d.device)
    last = torch.where(candidate, order, torch.zeros_like(order)).max(dim=1).values  # 0: no candidate
    return torch.cat([keep.new_full((1,), -1), keep])[last].reshape(height, width)


@torch.no_grad()
def reference_median_depth(median_ids, means, quats, scales, camera: Camera):
    """[H, W]: along each pixel's ray r (camera z = 1), the depth r^T A m / r^T A r where the median Gaussian (mean
    m, A the inverse of its covariance, in camera coordinates) peaks, within 3 of its largest scale of its centre's
    depth; 0 where the pixel has none."""
    height, width = median_ids.shape
    depth = torch.zeros(height, width, dtype=means.dtype, device=means.device)
    rotation = camera.world_to_camera[:3, :3].to(means.device, torch.float64)
    translation = camera.world_to_camera[:3, 3].to(means.device, torch.float64)
    for row, column in median_ids.ge(0).nonzero().tolist():
        g = int(median_ids[row, column])
        q = quats[g].detach().double() / torch.linalg.norm(quats[g].detach().double())
        w, x, y, z = q.tolist()
        local = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                              [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                              [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]],
                             dtype=torch.float64, device=means.device)
        scale = scales[g].detach().double()
        covariance = rotation @ local @ torch.diag(scale ** 2) @ local.T @ rotation.T
        inverse = torch.linalg.inv(covariance)
        mean = rotation @ means[g].detach().double() + translation
        ray = torch.tensor([(column + 0.5 - camera.cx) / camera.fx, (row + 0.5 - camera.cy) / camera.fy, 1.0],
                           dtype=torch.float64, device=means.device)
        peak = (ray @ inverse @ mean) / (ray @ inverse @ ray)
        reach = 3.0 * float(scale.max())
        depth[row, column] = float(min(max(peak, mean[2] - reach), mean[2] + reach))
    return depth


def reference_normals(means, quats, scales, camera: Camera):
    """[N, 3]: each Gaussian's normal in camera space, found another way than outputs/normals.py: the eigenvector of the
    smallest eigenvalue of its 3D covariance, seen from the camera, turned towards it."""
    _, vectors = torch.linalg.eigh(covariance_3d(quats, scales))  # eigenvalues ascending
    w2c = camera.world_to_camera.to(means.dtype)
    normal = vectors[:, :, 0] @ w2c[:3, :3].T
    center = means @ w2c[:3, :3].T + w2c[:3, 3]
    return normal * torch.where((normal * center).sum(dim=-1, keepdim=True) > 0, -1.0, 1.0).to(means.dtype)
