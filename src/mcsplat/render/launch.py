"""Runs the compositing kernels: Warp set-up, the multi-threaded CPU launcher, and the autograd Function.

On CPU one Warp launch runs on one core, so the image's tiles are cut into contiguous bands of about equal work and
the bands are launched from a thread pool (a CPU launch releases the GIL). Each worker owns a gradient buffer and a
fixed set of bands, so backward launches never write to the same memory at once and the result does not depend on
timing; the buffers are summed at the end in worker order. On CUDA the whole image
is one launch and the gradients are accumulated with atomics.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

from .binning import TileBins
from .kernels import PIXELS_PER_TILE, composite_kernels

_init_lock = threading.Lock()
_initialised = False
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_cpu_threads: int | None = None
BANDS_PER_THREAD = 4


def _cuda_driver_present() -> bool:
    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        with contextlib.suppress(OSError):
            ctypes.CDLL(name)
            return True
    return False


@contextlib.contextmanager
def _stderr_silenced():
    """Silence file descriptor 2 (native code writes there directly, bypassing sys.stderr)."""
    try:
        saved = os.dup(2)
    except OSError:  # no stderr at all
        yield
        return
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def ensure_warp() -> None:
    """Initialise Warp once, without its start-up banner or the no-CUDA-driver warning on CPU-only machines."""
    global _initialised
    if _initialised:
        return
    with _init_lock:
        if _initialised:
            return
        wp.config.log_level = wp.LOG_WARNING
        if _cuda_driver_present():
            wp.init()
        else:
            with _stderr_silenced():
                wp.init()
        _initialised = True


def set_cpu_threads(num_threads: int | None) -> None:
    """Threads for CPU compositing; None follows torch.get_num_threads()."""
    global _cpu_threads
    if num_threads is not None and num_threads < 1:
        raise ValueError(f"the number of CPU threads must be at least 1, got {num_threads}")
    _cpu_threads = num_threads


def cpu_threads() -> int:
    return _cpu_threads or max(1, torch.get_num_threads())


def _thread_pool(size: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    if _pool is None or _pool_size != size:
        if _pool is not None:
            _pool.shutdown(wait=True)
        _pool = ThreadPoolExecutor(max_workers=size, thread_name_prefix="mcsplat-raster")
        _pool_size = size
    return _pool


def _bands(tile_ranges: torch.Tensor, num_bands: int) -> list[tuple[int, int]]:
    """Contiguous [first, last) tile ranges of roughly equal work (pairs to walk plus a fixed cost per tile)."""
    work = (tile_ranges[:, 1] - tile_ranges[:, 0]).to(torch.float64) + 4.0
    cumulative = torch.cumsum(work, 0)
    targets = cumulative[-1] * torch.arange(1, num_bands, dtype=torch.float64) / num_bands
    cuts = torch.searchsorted(cumulative, targets).tolist()
    edges = [0] + cuts + [tile_ranges.shape[0]]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _wp(tensor: torch.Tensor) -> wp.array:
    return wp.from_torch(tensor.detach(), requires_grad=False)


def _run_bands(kernel, inputs_for_worker, num_tiles: int, tile_ranges: torch.Tensor, device: torch.device,
               num_workers: int) -> None:
    """Launch `kernel` over all tiles; `inputs_for_worker(w, first_tile)` gives the argument list of worker w."""
    if device.type == "cuda":
        with wp.ScopedStream(wp.stream_from_torch(device)):
            wp.launch(kernel, dim=num_tiles * PIXELS_PER_TILE, inputs=inputs_for_worker(0, 0),
                      device=wp.device_from_torch(device))
        return
    if num_workers == 1:
        wp.launch(kernel, dim=num_tiles * PIXELS_PER_TILE, inputs=inputs_for_worker(0, 0), device="cpu")
        return
    # Worker w launches bands w, w + W, w + 2W, ... in order: a fixed assignment, so every gradient buffer sums
    # the same values in the same order on every run (bitwise reproducible training and resume).
    bands = _bands(tile_ranges, num_workers * BANDS_PER_THREAD)

    def run(worker: int) -> None:
        for first, last in bands[worker::num_workers]:
            wp.launch(kernel, dim=(last - first) * PIXELS_PER_TILE, inputs=inputs_for_worker(worker, first),
                      device="cpu")

    for future in [_thread_pool(num_workers).submit(run, w) for w in range(num_workers)]:
        future.result()


def _num_workers(device: torch.device, num_tiles: int) -> int:
    return 1 if device.type == "cuda" else max(1, min(cpu_threads(), num_tiles))


class CompositeFunction(torch.autograd.Function):
    """(means2d, conics, opacities, colors, depths) -> (rgb [H,W,3], alpha [H,W], accumulated depth [H,W],
    contributed [N] bool). Gradients flow to the five per-Gaussian inputs."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, bins: TileBins, width: int,
                height: int):
        ensure_warp()
        dtype, device = means2d.dtype, means2d.device
        n = means2d.shape[0]
        inputs = [t.detach().contiguous() for t in (means2d, conics, opacities, colors, depths, background)]
        rgb = torch.empty(height, width, 3, dtype=dtype, device=device)
        transmittance = torch.empty(height, width, dtype=dtype, device=device)
        depth = torch.empty(height, width, dtype=dtype, device=device)
        last = torch.empty(height, width, dtype=torch.int32, device=device)
        contributed = torch.zeros(n, dtype=torch.int32, device=device)
        num_tiles = bins.tiles_x * bins.tiles_y
        forward_kernel, _ = composite_kernels(_warp_scalar(dtype))
        shared = [_wp(bins.tile_ranges), _wp(bins.gaussian_ids), _wp(bins.pair_masks)] + [_wp(t) for t in inputs]
        outputs = [_wp(rgb), _wp(transmittance), _wp(depth), _wp(last), _wp(contributed)]
        _run_bands(forward_kernel,
                   lambda worker, first_tile: [first_tile, bins.tiles_x, width, height] + shared + outputs,
                   num_tiles, bins.tile_ranges, device,
                   _num_workers(device, num_tiles))
        ctx.save_for_backward(*inputs, transmittance, last)
        ctx.bins, ctx.width, ctx.height = bins, width, height
        contributed = contributed.bool()
        ctx.mark_non_differentiable(contributed)
        return rgb, 1.0 - transmittance, depth, contributed

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha, grad_depth, _grad_contributed):
        means2d, conics, opacities, colors, depths, background, transmittance, last = ctx.saved_tensors
        bins, width, height = ctx.bins, ctx.width, ctx.height
        dtype, device = means2d.dtype, means2d.device
        n = means2d.shape[0]
        grads_in = [
            torch.zeros(height, width, 3, dtype=dtype, device=device) if grad_rgb is None else grad_rgb.contiguous(),
            torch.zeros(height, width, dtype=dtype, device=device) if grad_alpha is None else grad_alpha.contiguous(),
            torch.zeros(height, width, dtype=dtype, device=device) if grad_depth is None else grad_depth.contiguous(),
        ]
        num_tiles = bins.tiles_x * bins.tiles_y
        workers = _num_workers(device, num_tiles)
        # One set of gradient buffers per worker (means2d, conics, opacities, colors, depths).
        widths = (2, 3, 0, 3, 0)
        views = [[torch.zeros((n, k) if k else (n,), dtype=dtype, device=device) for k in widths]
                 for _ in range(workers)]
        per_worker = [[_wp(t) for t in parts] for parts in views]
        _, backward_kernel = composite_kernels(_warp_scalar(dtype))
        shared = ([_wp(bins.tile_ranges), _wp(bins.gaussian_ids), _wp(bins.pair_masks)]
                  + [_wp(t) for t in (means2d, conics, opacities, colors, depths, background, transmittance, last)]
                  + [_wp(g) for g in grads_in])
        _run_bands(backward_kernel,
                   lambda worker, first_tile: [first_tile, bins.tiles_x, width, height] + shared + per_worker[worker],
                   num_tiles, bins.tile_ranges, device, workers)
        totals = [sum(v[i] for v in views) if workers > 1 else views[0][i] for i in range(5)]
        return (*totals, None, None, None, None)


def _warp_scalar(dtype: torch.dtype):
    if dtype == torch.float32:
        return wp.float32
    if dtype == torch.float64:
        return wp.float64
    raise TypeError(f"the rasterizer supports float32 and float64 tensors, got {dtype}")
