"""Warp set-up and the multi-threaded CPU launcher that every compositing kernel goes through.

On CPU one Warp launch runs on one core, so the image's tiles are cut into contiguous bands of about equal work and
the bands are launched from a thread pool (a CPU launch releases the GIL). Each worker owns a gradient buffer and a
fixed set of bands, so backward launches never write to the same memory at once and the result does not depend on
timing; the buffers are summed at the end in worker order. On CUDA the whole image is one launch.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
import warp as wp

from .cpu_target import with_target

_init_lock = threading.Lock()
_initialised = False
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_cpu_threads: int | None = None
_split_small_work = False
BANDS_PER_THREAD = 4
# Below this many tiles a thread, one thread composites a step faster than two: handing a band to the pool and waiting
# for it costs more than the few tiles save (docs/measurements-log.md, "A small step on one thread", 2026-11-29).
MIN_TILES_PER_WORKER = 64


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
        # Launches with a block size above one run on the CPU as cooperative fibers, as CUDA blocks: the tile
        # kernels (render/composite/warp_tiles.py) are checked on the CPU this way. Other launches name no block size.
        wp.config.enable_cpu_blocks = True
        wp.config.cpu_compiler_flags = with_target(wp.config.cpu_compiler_flags)  # MCSPLAT_CPU_TARGET, if set
        if _cuda_driver_present():
            wp.init()
        else:
            with _stderr_silenced():
                wp.init()
        _initialised = True


def set_cpu_threads(num_threads: int | None, split_small_work: bool = False) -> None:
    """Threads for the CPU kernels; None follows torch.get_num_threads(). Work too small to pay for a thread's
    hand-off (MIN_TILES_PER_WORKER, ssim/cpu.py's ROWS_PER_THREAD) takes fewer of them, unless `split_small_work`:
    every thread takes a share however small (the tests that check the seams between the shares on small inputs)."""
    global _cpu_threads, _split_small_work
    if num_threads is not None and num_threads < 1:
        raise ValueError(f"the number of CPU threads must be at least 1, got {num_threads}")
    _cpu_threads, _split_small_work = num_threads, split_small_work


def splits_small_work() -> bool:
    """Whether set_cpu_threads asked every thread to take a share of small work too."""
    return _split_small_work


def cpu_threads() -> int:
    return _cpu_threads or max(1, torch.get_num_threads())


def thread_pool(size: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    if _pool is None or _pool_size != size:
        if _pool is not None:
            _pool.shutdown(wait=True)
        _pool = ThreadPoolExecutor(max_workers=size, thread_name_prefix="mcsplat-raster")
        _pool_size = size
    return _pool


def _bands(tile_ranges: torch.Tensor, num_bands: int) -> list[tuple[int, int]]:
    """Contiguous [first, last) tile ranges of roughly equal work (pairs to walk plus a fixed cost per tile). In numpy,
    on the host tensor's memory: a dozen small torch operators twice a step before (the sums are of whole numbers,
    exact either way, so the cuts are the same)."""
    ranges = tile_ranges.numpy()
    work = (ranges[:, 1] - ranges[:, 0]).astype(np.float64) + 4.0
    cumulative = np.cumsum(work)
    targets = cumulative[-1] * np.arange(1, num_bands, dtype=np.float64) / num_bands
    cuts = np.searchsorted(cumulative, targets).tolist()
    edges = [0] + cuts + [tile_ranges.shape[0]]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def warp_device(device: torch.device) -> wp.Device:
    """The Warp device of a torch device; a bare "cuda" is torch's current CUDA device, as torch reads it (Warp's
    device_from_torch needs the index)."""
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return _warp_device_of(device)


@functools.lru_cache(maxsize=16)
def _warp_device_of(device: torch.device) -> wp.Device:
    return wp.device_from_torch(device)


_warp_streams: dict[tuple[int, int], wp.Stream] = {}


def warp_stream(device: torch.device) -> wp.Stream:
    """torch's current stream on a CUDA device as a Warp stream, made once per stream: wp.stream_from_torch at every
    launch registers and unregisters the stream with Warp each time, host time a training step waits for."""
    stream = torch.cuda.current_stream(device)
    key = (stream.device_index, stream.cuda_stream)
    if key not in _warp_streams:
        _warp_streams[key] = wp.stream_from_torch(stream)  # holds the torch stream, which thus stays valid
    return _warp_streams[key]


def radix_sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int) -> None:
    """Warp's stable radix sort of the first `count` (key, value) pairs, in place (the tensors hold room for twice as
    many). On CUDA on torch's current stream, as the launches are: Warp's sort otherwise runs on Warp's own current
    stream, which a graph captured on torch's stream would not hold."""
    if keys.device.type != "cuda":
        wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(values), count, end_bit=end_bit)
        return
    with wp.ScopedStream(warp_stream(keys.device), sync_enter=False):
        wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(values), count, end_bit=end_bit)


def launch_on_cuda(kernel, dim, inputs: list, device: torch.device, block_dim: int | None = None,
                   tiled: bool = False) -> None:
    """One launch on torch's current stream of `device` (so that it runs in order with torch's own kernels)."""
    options = {} if block_dim is None else {"block_dim": block_dim}
    launch = wp.launch_tiled if tiled else wp.launch
    launch(kernel, dim=dim, inputs=inputs, device=warp_device(device), stream=warp_stream(device), **options)


def warp_view(tensor: torch.Tensor, dtype=None):
    """The tensor's memory as a Warp kernel argument (no copy): Warp's bare array descriptor, several times cheaper
    to make than a wp.array (about 80 per training step; on a GPU their making is time the step waits for). It
    reads the tensor's address, shape and strides only: no torch operator (a `detach` first was one per view)."""
    return wp.from_torch(tensor, dtype=dtype, requires_grad=False, return_ctype=True)


# Warp's bare array descriptor, what wp.from_torch(..., return_ctype=True) makes (wp.types.array_t before Warp 1.10).
array_t = type(wp.from_torch(torch.empty(0), return_ctype=True))


def flat_view(tensor: torch.Tensor):
    """`warp_view(tensor.reshape(-1))` of a contiguous tensor (a 1-d array of its elements) without the reshape's
    operator: the descriptor made from the address and the element count alone. For CPU launches: Warp checks
    neither the device nor the dtype of such a descriptor."""
    if tensor.device.type != "cpu":
        raise ValueError(f"flat_view is for CPU launches, got a tensor on {tensor.device}")
    if not tensor.is_contiguous():
        raise ValueError(f"flat_view needs a contiguous tensor, got strides {tensor.stride()}")
    scalar = wp.dtype_from_torch(tensor.dtype)
    view = array_t(tensor.data_ptr(), 0, 1, (tensor.numel(),), (ctypes.sizeof(scalar._type_),))
    view._ref = tensor  # the memory stays alive as long as the descriptor, as warp_view's does
    return view


def numpy_view(array: np.ndarray):
    """A contiguous 1-d numpy array as a Warp kernel argument (no copy, no torch operator): a small table the host
    fills before a CPU launch (addresses, sizes, learning rates)."""
    if array.ndim != 1 or not array.flags.c_contiguous:
        raise ValueError(f"numpy_view needs a contiguous 1-d array, got shape {array.shape}")
    view = array_t(array.ctypes.data, 0, 1, (array.shape[0],), (array.itemsize,))
    view._ref = array
    return view


def run_bands(kernel, inputs_for_worker, num_tiles: int, tile_ranges: torch.Tensor, device: torch.device,
              num_workers: int, threads_per_tile: int) -> None:
    """Launch `kernel` over all tiles, `threads_per_tile` Warp threads each (256: a thread per pixel; 1: a thread
    per tile); `inputs_for_worker(w, first_tile)` gives the argument list of worker w."""
    if device.type == "cuda":
        launch_on_cuda(kernel, num_tiles * threads_per_tile, inputs_for_worker(0, 0), device)
        return
    if num_workers == 1:
        wp.launch(kernel, dim=num_tiles * threads_per_tile, inputs=inputs_for_worker(0, 0), device="cpu")
        return
    # Worker w launches bands w, w + W, w + 2W, ... in order: a fixed assignment, so every gradient buffer sums
    # the same values in the same order on every run (bitwise reproducible training and resume).
    bands = _bands(tile_ranges, num_workers * BANDS_PER_THREAD)

    def run(worker: int) -> None:
        for first, last in bands[worker::num_workers]:
            wp.launch(kernel, dim=(last - first) * threads_per_tile, inputs=inputs_for_worker(worker, first),
                      device="cpu")

    for future in [thread_pool(num_workers).submit(run, w) for w in range(num_workers)]:
        future.result()


def run_tiled(kernel, num_blocks: int, arguments: list, device: torch.device, block_dim: int) -> None:
    """Launch a tile kernel as `num_blocks` blocks of `block_dim` threads, in one launch (on the CPU: one core)."""
    if num_blocks == 0:
        return
    if device.type == "cuda":
        launch_on_cuda(kernel, [num_blocks], arguments, device, block_dim, tiled=True)
        return
    wp.launch_tiled(kernel, dim=[num_blocks], inputs=arguments, block_dim=block_dim, device="cpu")


def num_workers_for(device: torch.device, num_tiles: int) -> int:
    """The CPU threads that composite `num_tiles` tiles: at least MIN_TILES_PER_WORKER each."""
    if device.type == "cuda":
        return 1
    return max(1, min(cpu_threads(), num_tiles // (1 if _split_small_work else MIN_TILES_PER_WORKER)))


def warp_scalar(dtype: torch.dtype):
    if dtype == torch.float32:
        return wp.float32
    if dtype == torch.float64:
        return wp.float64
    raise TypeError(f"the rasterizer supports float32 and float64 tensors, got {dtype}")


def run_ranges(kernel, n: int, device: torch.device, arguments: list, min_per_thread: int = 4096) -> None:
    """Launch a kernel whose first argument is an offset over items [0, n): on the CPU as contiguous ranges from the
    thread pool (each item is written by one thread only, so the result does not depend on timing), on CUDA as
    one launch."""
    if n == 0:
        return
    if device.type == "cuda":
        launch_on_cuda(kernel, n, [0] + arguments, device)
        return

    def run(first: int, last: int) -> None:
        wp.launch(kernel, dim=last - first, inputs=[first] + arguments, device="cpu")

    parts = max(1, min(cpu_threads(), n // max(1, min_per_thread)))
    edges = [n * k // parts for k in range(parts + 1)]
    if parts == 1:
        run(0, n)
        return
    for future in [thread_pool(parts).submit(run, a, b) for a, b in zip(edges[:-1], edges[1:])]:
        future.result()
