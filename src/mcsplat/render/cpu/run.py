"""Host side of the CPU's SIMD kernels: for the compositing, packs the per-Gaussian records, allocates outputs and
gradient buffers, and launches one Warp thread per tile through the banded CPU launcher (see compute/runtime.py); for
the projection, one Warp thread per chunk of 16 Gaussians over ranges of chunks."""

from __future__ import annotations

import torch

from ..binning import TileBins
from ...compute.runtime import flat_view, num_workers_for, run_bands, run_ranges
from .composite import (RECORD_WIDTH, composite_backward_simd, composite_forward_median_simd,
                        composite_forward_simd)
from .project import LANES, project_backward_simd, project_simd


def pack_records(means2d, conics, opacities, colors, depths) -> torch.Tensor:
    """[N, 10] rows (mean x, y, conic a, b, c, opacity, r, g, b, depth): one cache line per list entry."""
    return torch.cat([means2d, conics, opacities[:, None], colors, depths[:, None]], dim=1).contiguous()


_flat = flat_view  # the kernels take every array as a flat run of elements


def forward(records: torch.Tensor, background: torch.Tensor, bins: TileBins, width: int, height: int,
            with_median: bool = False):
    """-> rgb [H, W, 3], final transmittance [H, W], accumulated depth [H, W], last contributor [H, W] int32 (list
    position + 1 within the pixel's tile), contributed [N] int32, median Gaussian [H, W] int32 (-1 where none; None
    without with_median)."""
    n = records.shape[0]
    rgb = torch.empty(height, width, 3)
    transmittance = torch.empty(height, width)
    depth = torch.empty(height, width)
    last = torch.empty(height, width, dtype=torch.int32)
    contributed = torch.zeros(n, dtype=torch.int32)
    median = torch.empty(height, width, dtype=torch.int32) if with_median else None
    num_tiles = bins.tiles_x * bins.tiles_y
    arguments = [bins.tiles_x, width, height] + [_flat(t) for t in (
        bins.tile_ranges, bins.gaussian_ids, bins.pair_masks, records, background, rgb, transmittance, depth, last,
        contributed) + ((median,) if with_median else ())]
    kernel = composite_forward_median_simd if with_median else composite_forward_simd
    run_bands(kernel, lambda worker, first_tile: [first_tile] + arguments, num_tiles,
              bins.tile_ranges, records.device, num_workers_for(records.device, num_tiles), threads_per_tile=1)
    return rgb, transmittance, depth, last, contributed, median


def backward(records, background, transmittance, last, rgb, depth, grad_rgb, grad_alpha, grad_depth,
             bins: TileBins, width: int, height: int):
    """Gradients for (means2d [N, 2], conics [N, 3], opacities [N], colors [N, 3], depths [N])."""
    n = records.shape[0]
    num_tiles = bins.tiles_x * bins.tiles_y
    workers = num_workers_for(records.device, num_tiles)
    buffers = [torch.zeros(n, RECORD_WIDTH) for _ in range(workers)]
    arguments = [bins.tiles_x, width, height] + [_flat(t) for t in (
        bins.tile_ranges, bins.gaussian_ids, bins.pair_masks, records, background, transmittance, last, rgb, depth,
        grad_rgb, grad_alpha, grad_depth)]
    per_worker = [_flat(b) for b in buffers]
    run_bands(composite_backward_simd, lambda worker, first_tile: [first_tile] + arguments + [per_worker[worker]],
              num_tiles, bins.tile_ranges, records.device, workers, threads_per_tile=1)
    total = buffers[0]
    for extra in buffers[1:]:
        total = total + extra
    return (total[:, 0:2], total[:, 2:5], total[:, 5], total[:, 6:9], total[:, 9])


def _sh_layout(sh_dc: torch.Tensor, sh_rest: torch.Tensor, together: bool) -> list[int]:
    """(dc row stride, rest row stride, rest shift, rest count) in floats and coefficients: with `together`, sh_dc
    is sh_rest and holds every band [N, K, 3]; otherwise the DC band [N, 1, 3] and the rest [N, K - 1, 3]."""
    if together:
        k = sh_dc.shape[1]
        return [3 * k, 3 * k, 1, k - 1]
    return [3, 3 * sh_rest.shape[1], 0, sh_rest.shape[1]]


def _chunks(n: int) -> int:
    return -(-n // LANES)


def project(means, quats, scales, opacities, sh_dc, sh_rest, together: bool, camera: torch.Tensor, width: int,
            height: int, tiles_x: int, tiles_y: int, sh_degree: int, opacity_aware_radius: bool, antialiased: bool):
    """-> means2d [N, 2], conics [N, 3], depths [N], colours [N, 3], compensations [N] (1 unless antialiased), radii
    [N] int32, tile_min and tile_max [N, 2] int32, alpha_extent [N, 2]. `camera`: float32 numbers in
    project.CAMERA_LAYOUT's order. Inputs contiguous float32 on the CPU."""
    n = means.shape[0]
    outputs = [torch.empty(n, 2), torch.empty(n, 3), torch.empty(n), torch.empty(n, 3), torch.empty(n),
               torch.empty(n, dtype=torch.int32), torch.empty(n, 2, dtype=torch.int32),
               torch.empty(n, 2, dtype=torch.int32), torch.empty(n, 2)]
    dc_stride, rest_stride, rest_shift, _ = _sh_layout(sh_dc, sh_rest, together)
    run_ranges(project_simd, _chunks(n), means.device, [
        n, _flat(camera), width, height, tiles_x, tiles_y, sh_degree, int(opacity_aware_radius), int(antialiased),
        *(_flat(t) for t in (means, quats, scales, opacities, sh_dc, sh_rest)), dc_stride, rest_stride, rest_shift,
        *(_flat(t) for t in outputs)], min_per_thread=4096 // LANES)
    return outputs


def project_backward(means, quats, scales, sh_dc, sh_rest, together: bool, camera: torch.Tensor, width: int,
                     height: int, sh_degree: int, antialiased: bool, colors: torch.Tensor, upstream: list[torch.Tensor],
                     view_grad: bool):
    """Gradients for (means, quats, scales, sh_dc, sh_rest) from the upstream gradients of (means2d, conics, depths,
    colours, compensations), and with `view_grad` each Gaussian's share of the view matrix's [N, 12] (rotation
    row-major, translation), else None. `colors`: the forward's (the clamp at 0 passes no gradient where they are
    0). With `together` the SH gradient is one tensor, returned twice."""
    n = means.shape[0]
    grads = [torch.empty_like(t) for t in (means, quats, scales, sh_dc)]
    grads.append(grads[3] if together else torch.empty_like(sh_rest))
    per_gaussian_view = torch.empty(n if view_grad else 1, 12)
    run_ranges(project_backward_simd, _chunks(n), means.device, [
        n, _flat(camera), width, height, sh_degree, int(antialiased),
        *(_flat(t) for t in (means, quats, scales, sh_dc, sh_rest)), *_sh_layout(sh_dc, sh_rest, together),
        _flat(colors), *(_flat(t) for t in upstream), *(_flat(t) for t in grads), int(view_grad),
        _flat(per_gaussian_view)],
        min_per_thread=4096 // LANES)
    return grads, per_gaussian_view if view_grad else None
