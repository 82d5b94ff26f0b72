"""Differentiable Gaussian rasterizer: `render(gaussians, camera, background, sh_degree) -> RenderResult`.

Three stages, each a package holding its torch, Warp and CPU versions side by side. Projection and SH colour run in
one kernel (project/warp_kernel.py: SIMD kernels on the CPU, project/cpu_simd.py; a Warp kernel on CUDA and for
float64), binning in Warp kernels and radix sorts (bin/warp_kernels.py; C++ loops on the CPU, bin/cpu_loops.py), and
alpha compositing in Warp kernels with a hand-written backward (composite/function.py): SIMD kernels on the CPU
(composite/cpu_simd.py), tile kernels on CUDA (composite/warp_tiles.py), scalar kernels for float64 on the CPU
(composite/warp_scalar.py). The outputs given only when asked are in outputs/. Everything runs on every CPU core or on
CUDA, wherever the tensors are. The three stages are one choosable value (paths.py); the fixed numbers are in
constants.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Collection, Protocol, Sequence

import torch

from ..camera import Camera
from ..compute.runtime import cpu_threads, ensure_warp, set_cpu_threads
from ..geometry.sh import degree_from_bases
from .bin.pair_room import forget_rooms as forget_pair_rooms, sized_ahead as pairs_sized_ahead
from .bin.warp_kernels import TileBins
from .constants import FAR_PLANE, LOW_PASS, NEAR_PLANE, TILE_SIZE
from .outputs.passes import PassInputs, passes_for
from .paths import RenderPath, current_render_path

__all__ = ["render", "RenderResult", "Splats", "GaussiansLike", "set_cpu_threads", "cpu_threads", "ensure_warp",
           "training_kernels", "pairs_sized_ahead", "forget_pair_rooms"]


class GaussiansLike(Protocol):
    """What render() reads: activated parameters (GaussianModel and Splats both provide them)."""

    means: torch.Tensor      # [N, 3]
    quats: torch.Tensor      # [N, 4] (w, x, y, z), need not be normalised
    scales: torch.Tensor     # [N, 3] activated (positive)
    opacities: torch.Tensor  # [N] activated, in [0, 1]
    sh: torch.Tensor         # [N, K, 3] SH coefficients, K = (degree + 1)^2
    # Optional (read with getattr, False when absent): drawn with Mip-Splatting's 2D filter (--antialiased). A scene
    # trained with the filter is meant to be seen through it, so the flag travels with the Gaussians.
    # antialiased: bool


@dataclass
class Splats:
    """A plain bundle of activated Gaussian parameters."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    antialiased: bool = False


@dataclass
class RenderResult:
    rgb: torch.Tensor          # [H, W, 3], composited over the background
    alpha: torch.Tensor        # [H, W] accumulated opacity
    depth_sum: torch.Tensor    # [H, W] alpha-weighted sum of camera z (`depth` divides it by alpha)
    means2d: torch.Tensor      # [N, 2] screen-space means; .grad is kept after backward (for ADC)
    radii: torch.Tensor        # [N] int32 pixel radius, 0 where culled
    depths: torch.Tensor       # [N] camera-space z of each Gaussian
    contributed: torch.Tensor  # [N] bool: the Gaussian was composited into at least one pixel
    # The outputs given only when asked (render(outputs={...}); outputs/passes.py), else None:
    # [H, W] "median_depth": the depth along the pixel's ray where the Gaussian at which the accumulated alpha first
    # reaches 0.5 (the last one composited where it never does) is densest; 0 where none is composited. No gradient.
    median_depth: torch.Tensor | None = None
    # [H, W, 3] "normals": each Gaussian's camera-space normal (its shortest axis, facing the camera) composited like
    # the colour over zero, with gradients. A second compositing pass.
    normal: torch.Tensor | None = None
    # [H, W] "planar_depth": where each pixel's ray meets the plane of its composited normal and plane distance
    # (PGSR's unbiased depth), with gradients; 0 where none. The plane distances ride in the normal map's pass.
    planar_depth: torch.Tensor | None = None
    # [H, W] "distortion": 2DGS's depth distortion, sum over the pixel's pairs of Gaussians of w_i w_j (1/z_i -
    # 1/z_j)^2 (units^-2), with gradients. A compositing pass of its own.
    distortion: torch.Tensor | None = None
    bins: TileBins | None = None  # the per-tile lists the render composited

    @cached_property
    def depth(self) -> torch.Tensor:
        """[H, W] expected depth: the alpha-weighted mean camera z, 0 where alpha is 0. Divided on first use (with
        gradients where the render has them): a training step whose loss reads no depth skips the division."""
        return torch.where(self.alpha > 0, self.depth_sum / torch.clamp(self.alpha, min=1e-10),
                           torch.zeros_like(self.depth_sum))

    @property
    def num_pairs(self) -> int:
        """(tile, Gaussian) intersections; read from the device when the lists sit in a room (a training step's)."""
        return 0 if self.bins is None else self.bins.num_pairs

    @property
    def visible(self) -> torch.Tensor:
        """[N] bool: inside the view frustum and covering at least one tile."""
        return self.radii > 0


def render(gaussians: GaussiansLike, camera: Camera, background: Sequence[float] | torch.Tensor | None = None,
           sh_degree: int | None = None, *, outputs: Collection[str] = (), near: float = NEAR_PLANE,
           far: float = FAR_PLANE, eps2d: float = LOW_PASS, opacity_aware_radius: bool = False,
           path: RenderPath | None = None, antialiased: bool | None = None) -> RenderResult:
    """Render one view. `sh_degree` None uses every SH coefficient given; `background` defaults to black; `outputs`
    the outputs given only on request, besides the colour, alpha and depth ("median_depth", "normals",
    "planar_depth", "distortion": outputs/passes.py, each a pass that a render without it does not run); `path`
    the stages to run (default: current_render_path(), the kernels unless a caller chose otherwise); `antialiased`
    draws with Mip-Splatting's 2D filter (None: as the Gaussians' own `antialiased` flag says)."""
    asked = frozenset(outputs)
    passes = passes_for(asked)
    stages = path or current_render_path()
    means, quats, scales, opacities = gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities
    sh, sh_rest = _sh_arrays(gaussians)
    _check_inputs(means, quats, scales, opacities, sh, sh_rest)
    dtype, device = means.dtype, means.device
    max_degree = degree_from_bases(sh.shape[1] + (0 if sh_rest is None else sh_rest.shape[1]))
    degree = max_degree if sh_degree is None else sh_degree
    if not 0 <= degree <= max_degree:
        raise ValueError(f"sh_degree must be in 0..{max_degree} for these coefficients, got {sh_degree}")
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else \
        torch.as_tensor(background, dtype=dtype, device=device).reshape(3)

    if antialiased is None:
        antialiased = bool(getattr(gaussians, "antialiased", False))
    projection, colors = stages.project(means, quats, scales, opacities, sh, camera, degree, sh_rest=sh_rest,
                                        near=near, far=far, eps2d=eps2d, opacity_aware_radius=opacity_aware_radius,
                                        antialiased=antialiased)
    if projection.compensations is not None:
        opacities = opacities * projection.compensations
    means2d = projection.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    tiles_x = -(-camera.width // TILE_SIZE)
    tiles_y = -(-camera.height // TILE_SIZE)
    bins: TileBins = stages.bin(projection.tile_min, projection.tile_max, projection.depths, projection.radii,
                                tiles_x, tiles_y, means2d=means2d, alpha_extent=projection.alpha_extent)
    with_median = any(output_pass.needs_median_ids for output_pass in passes)
    rgb, alpha, depth_sum, contributed, *median_ids = stages.composite(
        means2d, projection.conics, opacities, colors, projection.depths, bg, bins, camera.width, camera.height,
        **({"median_gaussian": True} if with_median else {}))

    def composited(values: torch.Tensor, scalars: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return stages.composite(means2d, projection.conics, opacities, values, scalars, torch.zeros_like(bg), bins,
                                camera.width, camera.height)[:3]

    inputs = PassInputs(means, quats, scales, opacities, camera, near, composited,
                        median_ids[0] if with_median else None)
    given = {field: value for output_pass in passes for field, value in output_pass.run(inputs, asked).items()}
    return RenderResult(rgb=rgb, alpha=alpha, depth_sum=depth_sum, means2d=means2d, radii=projection.radii,
                        depths=projection.depths, contributed=contributed, bins=bins, **given)


def _sh_arrays(gaussians: GaussiansLike) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(all coefficients, None), or (DC band, the rest) from a model that keeps them apart (no concatenation)."""
    parts = getattr(gaussians, "sh_parts", None)
    return parts if parts is not None else (gaussians.sh, None)


def _check_inputs(means, quats, scales, opacities, sh, sh_rest=None) -> None:
    n = means.shape[0]
    expected = {"means": (means, (n, 3)), "quats": (quats, (n, 4)), "scales": (scales, (n, 3)),
                "opacities": (opacities, (n,))}
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"render: {name} must have shape {list(shape)}, got {list(tensor.shape)}")
    if sh.dim() != 3 or sh.shape[0] != n or sh.shape[2] != 3:
        raise ValueError(f"render: sh must have shape [{n}, K, 3], got {list(sh.shape)}")
    if sh_rest is not None and (sh.shape[1] != 1 or sh_rest.dim() != 3 or sh_rest.shape[0] != n
                                or sh_rest.shape[2] != 3):
        raise ValueError(f"render: split SH must be [{n}, 1, 3] and [{n}, K - 1, 3], got {list(sh.shape)} and "
                         f"{list(sh_rest.shape)}")
    extra = () if sh_rest is None else (("sh_rest", sh_rest),)
    for name, tensor in (("quats", quats), ("scales", scales), ("opacities", opacities), ("sh", sh), *extra):
        if tensor.dtype != means.dtype or tensor.device != means.device:
            raise ValueError(f"render: {name} is {tensor.dtype} on {tensor.device}, but means are {means.dtype} "
                             f"on {means.device}; all parameters must share one dtype and device")


def training_kernels(device: torch.device, dtype: torch.dtype = torch.float32) -> list:
    """The Warp kernels one render and its backward launch on `device` (compute.compile loads them ahead)."""
    from ..compute.runtime import warp_scalar
    from .bin import cpu_loops, warp_kernels as bin_warp
    from .composite import cpu_simd as composite_simd, warp_scalar as composite_scalar, warp_tiles
    from .kernel_choice import kernels_for
    from .project import cpu_simd as project_simd, warp_kernel as project_warp

    scalar = warp_scalar(dtype)
    choice = kernels_for(torch.empty(0, dtype=dtype, device=device))
    if choice == "simd":
        return [project_simd.project_simd, project_simd.project_backward_simd, cpu_loops.count_pairs_cpu,
                cpu_loops.depth_slots_cpu, cpu_loops.write_pairs_cpu, cpu_loops.sort_split_cpu,
                composite_simd.composite_forward_simd, composite_simd.composite_backward_simd,
                composite_simd.pack_records_simd, composite_simd.sum_gradient_rows_simd]
    found = [*project_warp.projection_kernels(scalar), bin_warp._count_pairs, bin_warp._write_pairs,
             bin_warp._tile_ranges]
    if choice == "tile":
        return found + [warp_tiles.forward_kernel(scalar), warp_tiles.backward_kernel(scalar)]
    return found + list(composite_scalar.composite_kernels(scalar))
