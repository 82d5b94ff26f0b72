"""Host side of the SIMD compositing kernels: packs the per-Gaussian records, allocates outputs and gradient
buffers, and launches one Warp thread per tile through the banded CPU launcher (see render/runtime.py)."""

from __future__ import annotations

import torch

from ..binning import TileBins
from ...compute.runtime import num_workers_for, run_bands, warp_view
from .composite import (RECORD_WIDTH, composite_backward_simd, composite_forward_median_simd,
                        composite_forward_simd)


def pack_records(means2d, conics, opacities, colors, depths) -> torch.Tensor:
    """[N, 10] rows (mean x, y, conic a, b, c, opacity, r, g, b, depth): one cache line per list entry."""
    return torch.cat([means2d, conics, opacities[:, None], colors, depths[:, None]], dim=1).contiguous()


def _flat(tensor: torch.Tensor):
    return warp_view(tensor.reshape(-1))


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
