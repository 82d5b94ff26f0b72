"""The compositing step as a torch.autograd.Function, and the choice of kernels for it.

float32 tensors on the CPU get the SIMD kernels of render/cpu/ (a 4x4 pixel block per vector); float64 and CUDA get
the scalar Warp kernels of kernels.py (a thread per pixel). `set_cpu_kernels("scalar")` forces the scalar kernels on
the CPU too: the benchmarks' in-process baseline, and the tests' second opinion.
"""

from __future__ import annotations

import torch

from ..compute.runtime import (cpu_threads, ensure_warp, num_workers_for, run_bands, set_cpu_threads, warp_scalar,
                      warp_view)
from .binning import TileBins
from .constants import PIXELS_PER_TILE
from .cpu import run as simd
from .kernels import composite_kernels, median_forward_kernel

__all__ = ["CompositeFunction", "composite", "set_cpu_kernels", "cpu_kernels", "ensure_warp", "set_cpu_threads",
           "cpu_threads"]

CPU_KERNELS = ("simd", "scalar")
_cpu_kernels = "simd"


def set_cpu_kernels(name: str) -> None:
    """'simd' (the default) or 'scalar': which compositing kernels float32 renders on the CPU use."""
    global _cpu_kernels
    if name not in CPU_KERNELS:
        raise ValueError(f"CPU kernels must be one of {', '.join(CPU_KERNELS)}, got {name!r}")
    _cpu_kernels = name


def cpu_kernels() -> str:
    return _cpu_kernels


def _uses_simd(tensor: torch.Tensor, kernels: str | None) -> bool:
    return tensor.device.type == "cpu" and tensor.dtype == torch.float32 and (kernels or _cpu_kernels) == "simd"


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
        ctx.simd = _uses_simd(means2d, cpu_kernels)
        inputs = [t.detach().contiguous() for t in (means2d, conics, opacities, colors, depths, background)]
        if ctx.simd:
            records = simd.pack_records(*inputs[:5])
            rgb, transmittance, depth, last, contributed, median = simd.forward(records, inputs[5], bins, width,
                                                                                height, median_gaussian)
            ctx.save_for_backward(records, inputs[5], transmittance, last, rgb, depth)
        else:
            rgb, transmittance, depth, last, contributed, median = _scalar_forward(inputs, bins, width, height,
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
        like = saved[-1]  # an [H, W] tensor of the right dtype and device
        grads_in = [
            torch.zeros(height, width, 3, dtype=like.dtype, device=like.device) if grad_rgb is None
            else grad_rgb.contiguous(),
            torch.zeros_like(like) if grad_alpha is None else grad_alpha.contiguous(),
            torch.zeros_like(like) if grad_depth is None else grad_depth.contiguous(),
        ]
        if ctx.simd:
            records, background, transmittance, last, rgb, depth = saved
            totals = simd.backward(records, background, transmittance, last, rgb, depth, *grads_in, bins, width,
                                   height)
        else:
            totals = _scalar_backward(saved, grads_in, bins, width, height)
        return (*totals, None, None, None, None, None, None)


def composite(means2d, conics, opacities, colors, depths, background, bins: TileBins, width: int, height: int, *,
              cpu_kernels: str | None = None, median_gaussian: bool = False):
    """CompositeFunction with its options by name (autograd's apply takes an option only after all those before it)."""
    return CompositeFunction.apply(means2d, conics, opacities, colors, depths, background, bins, width, height,
                                   cpu_kernels, median_gaussian)


def _scalar_forward(inputs, bins: TileBins, width: int, height: int, with_median: bool):
    means2d = inputs[0]
    dtype, device = means2d.dtype, means2d.device
    rgb = torch.empty(height, width, 3, dtype=dtype, device=device)
    transmittance = torch.empty(height, width, dtype=dtype, device=device)
    depth = torch.empty(height, width, dtype=dtype, device=device)
    last = torch.empty(height, width, dtype=torch.int32, device=device)
    contributed = torch.zeros(means2d.shape[0], dtype=torch.int32, device=device)
    # The plain kernel takes the median's array too and never touches it: one element stands in.
    median = torch.empty((height, width) if with_median else (1, 1), dtype=torch.int32, device=device)
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
