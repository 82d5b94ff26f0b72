"""The compositing step as a torch.autograd.Function, on the kernels kernel_choice.py chooses.

float32 tensors on the CPU get the SIMD kernels of cpu_simd.py (a 4x4 pixel block per vector), float64 on the CPU
the scalar Warp kernels of warp_scalar.py (a thread per pixel), and CUDA the tile kernels of warp_tiles.py (a block of
threads per tile, batches of Gaussians in shared memory). The choice's functions are re-exported here.
"""

from __future__ import annotations

import functools

import torch

from ...compute.runtime import (cpu_threads, ensure_warp, num_workers_for, run_bands, run_tiled, set_cpu_threads,
                               warp_scalar, warp_view)
from ..bin.warp_kernels import TileBins
from ..kernel_choice import cpu_kernels, cuda_kernels, kernels_for, set_cpu_kernels, set_cuda_kernels
from ..constants import PIXELS_PER_TILE
from . import cpu_simd as simd
from . import warp_tiles
from .warp_scalar import composite_kernels, median_forward_kernel

__all__ = ["CompositeFunction", "composite", "set_cpu_kernels", "cpu_kernels", "set_cuda_kernels", "cuda_kernels",
           "kernels_for", "ensure_warp", "set_cpu_threads", "cpu_threads"]


class CompositeFunction(torch.autograd.Function):
    """(means2d, conics, opacities, colors, depths) -> (rgb [H,W,3], alpha [H,W], accumulated depth [H,W],
    contributed [N] bool), and with `median_gaussian=True` a fifth output: per pixel, the Gaussian at which the
    accumulated alpha first reaches 0.5 ([H,W] int32, -1 where none; the forward kernels that find it are separate
    ones, so that a render without it costs what it did). Gradients flow to the five per-Gaussian inputs.
    `cpu_kernels` ('simd' or 'scalar') overrides set_cpu_kernels() for this call."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, bins: TileBins, width: int,
                height: int, cpu_kernels: str | None = None, median_gaussian: bool = False):
        ensure_warp()
        ctx.set_materialize_grads(False)  # the backward takes None (no zeros made for the outputs without gradient)
        ctx.kernels = kernels_for(means2d, cpu_kernels)
        # No detach: the forward runs without grad mode, and the kernels take the memory (compute.runtime's views).
        inputs = [t.contiguous() for t in (means2d, conics, opacities, colors, depths, background)]
        if ctx.kernels == "simd":
            records = simd.pack_records(*inputs[:5])
            rgb, transmittance, depth, last, contributed, median = simd.forward(records, inputs[5], bins, width,
                                                                                height, median_gaussian)
            ctx.save_for_backward(records, inputs[5], transmittance, last, rgb, depth)
        else:
            forward = _tile_forward if ctx.kernels.startswith("tile") else _scalar_forward
            rgb, transmittance, depth, last, contributed, median = forward(inputs, bins, width, height,
                                                                           median_gaussian)
            ctx.save_for_backward(*inputs, transmittance, last)
        ctx.bins, ctx.width, ctx.height = bins, width, height
        not_differentiable = (contributed.bool(),) + (() if median is None else (median,))
        ctx.mark_non_differentiable(*not_differentiable)
        return (rgb, 1.0 - transmittance, depth) + not_differentiable

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha, grad_depth, _grad_contributed, *_grad_median):
        bins, width, height = ctx.bins, ctx.width, ctx.height
        saved = ctx.saved_tensors
        zeros = functools.partial(torch.zeros, dtype=saved[0].dtype, device=saved[0].device)  # the inputs' dtype
        grads_in = [
            zeros(height, width, 3) if grad_rgb is None else grad_rgb.contiguous(),
            zeros(height, width) if grad_alpha is None else grad_alpha.contiguous(),
            zeros(height, width) if grad_depth is None else grad_depth.contiguous(),
        ]
        if ctx.kernels == "simd":
            records, background, transmittance, last, rgb, depth = saved
            totals = simd.backward(records, background, transmittance, last, rgb, depth, *grads_in, bins, width,
                                   height)
        elif ctx.kernels.startswith("tile"):
            totals = _tile_backward(saved, grads_in, bins, width, height, skip_unused=ctx.kernels == "tile")
        else:
            totals = _scalar_backward(saved, grads_in, bins, width, height)
        return (*totals, None, None, None, None, None, None)


def composite(means2d, conics, opacities, colors, depths, background, bins: TileBins, width: int, height: int, *,
              cpu_kernels: str | None = None, median_gaussian: bool = False):
    """CompositeFunction with its options by name (autograd's apply takes an option only after all those before it)."""
    return CompositeFunction.apply(means2d, conics, opacities, colors, depths, background, bins, width, height,
                                   cpu_kernels, median_gaussian)


def _forward_outputs(means2d: torch.Tensor, width: int, height: int, with_median: bool) -> list[torch.Tensor]:
    """(rgb, transmittance, depth, last contributor, contributed, median Gaussian) for a forward kernel to fill."""
    dtype, device = means2d.dtype, means2d.device
    # The plain kernels take the median's array too and never touch it: one element stands in.
    return [torch.empty(height, width, 3, dtype=dtype, device=device),
            torch.empty(height, width, dtype=dtype, device=device),
            torch.empty(height, width, dtype=dtype, device=device),
            torch.empty(height, width, dtype=torch.int32, device=device),
            torch.zeros(means2d.shape[0], dtype=torch.int32, device=device),
            torch.empty((height, width) if with_median else (1, 1), dtype=torch.int32, device=device)]


def _bins_views(bins: TileBins) -> list:
    return [warp_view(bins.tile_ranges), warp_view(bins.gaussian_ids), warp_view(bins.pair_masks)]


def _tile_forward(inputs, bins: TileBins, width: int, height: int, with_median: bool):
    means2d = inputs[0]
    outputs = _forward_outputs(means2d, width, height, with_median)
    kernel = warp_tiles.forward_kernel(warp_scalar(means2d.dtype), with_median)
    arguments = ([bins.tiles_x, width, height] + _bins_views(bins) + [warp_view(t) for t in inputs]
                 + [warp_view(t) for t in outputs])
    run_tiled(kernel, bins.tiles_x * bins.tiles_y, arguments, means2d.device, warp_tiles.FORWARD_BLOCK)
    rgb, transmittance, depth, last, contributed, median = outputs
    return rgb, transmittance, depth, last, contributed, median if with_median else None


def _tile_backward(saved, grads_in, bins: TileBins, width: int, height: int, skip_unused: bool = True):
    means2d = saved[0]
    dtype = means2d.dtype
    record = warp_tiles.record_type(warp_scalar(dtype))
    grads = torch.zeros(means2d.shape[0], warp_tiles.GRADIENT_WIDTH, dtype=dtype, device=means2d.device)
    arguments = ([bins.tiles_x, width, height] + _bins_views(bins) + [warp_view(t) for t in saved]
                 + [warp_view(g) for g in grads_in] + [warp_view(grads, record)])
    run_tiled(warp_tiles.backward_kernel(warp_scalar(dtype), skip_unused),
              bins.tiles_x * bins.tiles_y * warp_tiles.BACKWARD_BLOCKS_PER_TILE, arguments, means2d.device,
              warp_tiles.BACKWARD_BLOCK)
    # Views into the one buffer, in the order of CompositeFunction's inputs; opacities and depths lose their column.
    columns = [warp_tiles.GRADIENT_COLUMNS[name] for name in ("means2d", "conics", "opacities", "colors", "depths")]
    views = [grads[:, a:b] for a, b in columns]
    return [views[0], views[1], views[2][:, 0], views[3], views[4][:, 0]]


def _scalar_forward(inputs, bins: TileBins, width: int, height: int, with_median: bool):
    means2d = inputs[0]
    dtype, device = means2d.dtype, means2d.device
    rgb, transmittance, depth, last, contributed, median = _forward_outputs(means2d, width, height, with_median)
    num_tiles = bins.tiles_x * bins.tiles_y
    forward_kernel = median_forward_kernel(warp_scalar(dtype)) if with_median else \
        composite_kernels(warp_scalar(dtype))[0]
    shared = [warp_view(bins.tile_ranges), warp_view(bins.gaussian_ids), warp_view(bins.pair_masks)]
    shared += [warp_view(t) for t in inputs]
    outputs = [warp_view(t) for t in (rgb, transmittance, depth, last, contributed, median)]
    run_bands(forward_kernel, lambda worker, first_tile: [first_tile, bins.tiles_x, width, height] + shared + outputs,
              num_tiles, bins.tile_ranges, device, num_workers_for(device, num_tiles), PIXELS_PER_TILE)
    return rgb, transmittance, depth, last, contributed, median if with_median else None


def _scalar_backward(saved, grads_in, bins: TileBins, width: int, height: int):
    means2d, conics, opacities, colors, depths, background, transmittance, last = saved
    dtype, device = means2d.dtype, means2d.device
    n = means2d.shape[0]
    num_tiles = bins.tiles_x * bins.tiles_y
    workers = num_workers_for(device, num_tiles)
    # One set of gradient buffers per worker (means2d, conics, opacities, colors, depths).
    widths = (2, 3, 0, 3, 0)
    views = [[torch.zeros((n, k) if k else (n,), dtype=dtype, device=device) for k in widths]
             for _ in range(workers)]
    per_worker = [[warp_view(t) for t in parts] for parts in views]
    _, backward_kernel = composite_kernels(warp_scalar(dtype))
    shared = ([warp_view(bins.tile_ranges), warp_view(bins.gaussian_ids), warp_view(bins.pair_masks)]
              + [warp_view(t) for t in (means2d, conics, opacities, colors, depths, background, transmittance, last)]
              + [warp_view(g) for g in grads_in])
    run_bands(backward_kernel,
              lambda worker, first_tile: [first_tile, bins.tiles_x, width, height] + shared + per_worker[worker],
              num_tiles, bins.tile_ranges, device, workers, PIXELS_PER_TILE)
    return [sum(v[i] for v in views) if workers > 1 else views[0][i] for i in range(5)]
