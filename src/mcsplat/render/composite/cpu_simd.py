"""SIMD alpha compositing for the CPU: one 4x4 pixel block in 16 vector lanes, forward and hand-written backward.

Same rules and outputs as the scalar kernels of warp_scalar.py (which stay the CUDA path, the float64 path and the
benchmark's baseline), but one kernel thread per tile, walking the tile's list Gaussian by Gaussian: each list entry
is read once and applied to every 4x4 block its mask bit marks, 16 pixels at a time. Warp's kernel language does not
vectorise this loop on the CPU, so the tile bodies are C++ snippets (`wp.func_native`) with clang vector types,
compiled by the clang inside the warp-lang wheel. They never reach the CUDA compiler: this file is its own Warp
module and is only ever launched on the CPU.

The backward walks front to back, so the transmittance T_i in front of Gaussian i is the forward's own product (no
division). With h_i = c_i . g_rgb + z_i g_depth and S_i = sum_{j <= i} alpha_j T_j h_j, the gradient of the loss
with respect to alpha_i is

    dL/dalpha_i = T_i h_i - (R - S_i) / (1 - alpha_i),   R = S_total - T_final (g_alpha - background . g_rgb)

where S_total = C_fg . g_rgb + D g_depth comes from the forward's outputs (C_fg the colour before the background, D
the accumulated depth). The 10 gradient sums of a Gaussian (mean x, y, conic a, b, c, opacity, colour r, g, b, depth)
are kept as vectors over all of its blocks and reduced across lanes once per (tile, Gaussian). Warp compiles for the
host (-march=native) and keys its kernel cache by the host's ISA, so a binary built for one CPU is never handed to
another.

Record layout: `records` is [N, 10] float32 rows (mean x, mean y, conic a, b, c, opacity, r, g, b, depth), packed once
per render so that a list entry costs one cache line; `grads` uses the same column order.

The C++ of the tile bodies is in the cpu_simd_*.cpp and .h files beside this module; the host side (the records, the
outputs and gradient buffers, the launches) is at the end of it.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
import warp as wp

from ...compute.cpp_snippets import read_snippet
from ...compute.cpu_target import kernel_flags
from ...compute.runtime import flat_view, num_workers_for, numpy_view, run_bands, run_ranges
from ...compute.simd_lanes import SIMD_MATH
from ..bin.warp_kernels import TileBins
from ..constants import (ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, MEDIAN_TRANSMITTANCE, POWER_SKIP, TILE_SIZE,
                         TRANSMITTANCE_MIN)

# The tile bodies hold a tile as 16 blocks of 16 lanes: they are written for 16x16 tiles of 4x4 blocks.
assert TILE_SIZE == 16 and BLOCK_SIZE == 4, "the SIMD tile body needs 16x16 tiles of 4x4 pixel blocks"

RECORD_WIDTH = 10
# How many list entries ahead the tile bodies ask for a record (and its gradient row): about a memory latency of work.
PREFETCH_DISTANCE = 8

# The C++ is in cpu_simd_*.cpp and .h. The prelude holds the types and helpers both tile bodies share (masks are int
# vectors of 0 / -1, clang's vector comparisons) and the tile's blocks.
_PRELUDE = read_snippet(__package__, "cpu_simd_prelude.h", {
    "SIMD_MATH": SIMD_MATH, "ALPHA_MIN": ALPHA_MIN, "ALPHA_MAX": ALPHA_MAX, "PREFETCH_DISTANCE": PREFETCH_DISTANCE,
    "POWER_SKIP": POWER_SKIP, "TRANSMITTANCE_MIN": TRANSMITTANCE_MIN, "TILE_SIZE": TILE_SIZE})


def _list_entry(gradient_rows: str) -> str:
    """List entry k of the tile's walk (`for k` from start to end): asks for the record PREFETCH_DISTANCE entries ahead
    (and, backward, its row of `gradient_rows`), skips the entry where its mask marks no active block, and otherwise
    holds the Gaussian g, its record `row` and the scalars mx, my, ca, cb, cc, opacity."""
    return read_snippet(__package__, "cpu_simd_entry.h", {"GRADIENT_ROWS": gradient_rows})


def _evaluate_block(taking_part: str) -> str:
    """Evaluates one Gaussian (scalars mx, my, ca, cb, cc, opacity) on block b in two steps: the power, and the lanes
    where it is in [power_skip, 0]; then, only where some lane that still takes part (`taking_part`) is in range, the
    exponential, alpha and the lanes that pass the exact tests of the scalar kernel (power in range, alpha >= 1/255)."""
    return read_snippet(__package__, "cpu_simd_block.h", {"TAKING_PART": taking_part})


# The median Gaussian (warp_scalar.py): the last one composited while the transmittance in front of it is still
# above MEDIAN_TRANSMITTANCE (-1 where none is), one vector of ids per block: lines the forward takes at its
# {{MEDIAN_*}} marks.
_MEDIAN_LINES = {"MEDIAN_DECLARE": "cpu_simd_median_declare.h", "MEDIAN_UPDATE": "cpu_simd_median_update.h",
                 "MEDIAN_STORE": "cpu_simd_median_store.h"}


def _forward_body(with_median: bool) -> str:
    """The forward tile body, with the median's lines or (the training kernel) without."""
    median = {mark: read_snippet(__package__, name, {"MEDIAN_TRANSMITTANCE": MEDIAN_TRANSMITTANCE}) if with_median
              else "" for mark, name in _MEDIAN_LINES.items()}
    return read_snippet(__package__, "cpu_simd_forward.cpp", {
        "PRELUDE": _PRELUDE, "LIST_ENTRY": _list_entry("nullptr"), "EVALUATE_BLOCK": _evaluate_block("~done[b]"),
        **median})


_BACKWARD_BODY = read_snippet(__package__, "cpu_simd_backward.cpp", {
    "PRELUDE": _PRELUDE, "LIST_ENTRY": _list_entry("grads_"), "EVALUATE_BLOCK": _evaluate_block("last[b] > index")})

# 512-bit vectors where the CPU has them (clang otherwise splits a 16-lane vector into two 256-bit halves; on AVX2 the
# 16 lanes take two registers each, and 8-lane vectors over half-blocks measured no faster there). Fused multiply-add
# (Warp's default keeps a * b + c as two roundings) makes the kernels about 10% faster.
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512 -ffp-contract=fast")})

_int_array = wp.array(dtype=wp.int32)
_float_array = wp.array(dtype=wp.float32)
_byte_array = wp.array(dtype=wp.uint8)  # a torch bool tensor's bytes


@wp.func_native(_forward_body(with_median=False))
def _composite_tile_forward(tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                            gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                            background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                            out_depth: _float_array, out_last: _int_array, contributed: _byte_array): ...


@wp.func_native(_forward_body(with_median=True))
def _composite_tile_forward_median(tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                                   gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                                   background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                                   out_depth: _float_array, out_last: _int_array, contributed: _byte_array,
                                   out_median: _int_array): ...


@wp.func_native(_BACKWARD_BODY)
def _composite_tile_backward(tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                             gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                             background: _float_array, final_transmittance: _float_array,
                             last_contributor: _int_array, out_rgb: _float_array, out_depth: _float_array,
                             grad_rgb: _float_array, grad_alpha: _float_array, grad_depth: _float_array,
                             grads: _float_array): ...


@wp.kernel
def composite_forward_simd(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                           gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                           background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                           out_depth: _float_array, out_last: _int_array, contributed: _byte_array):
    """One thread per tile of the band that starts at `first_tile`."""
    _composite_tile_forward(first_tile + wp.tid(), tiles_x, width, height, tile_ranges, gaussian_ids, pair_masks,
                            records, background, out_rgb, out_transmittance, out_depth, out_last, contributed)


@wp.kernel
def composite_forward_median_simd(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                                  gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                                  background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                                  out_depth: _float_array, out_last: _int_array, contributed: _byte_array,
                                  out_median: _int_array):
    """The forward that also writes each pixel's median Gaussian (forward only: no loss uses it)."""
    _composite_tile_forward_median(first_tile + wp.tid(), tiles_x, width, height, tile_ranges, gaussian_ids,
                                   pair_masks, records, background, out_rgb, out_transmittance, out_depth, out_last,
                                   contributed, out_median)


@wp.kernel
def composite_backward_simd(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                            gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                            background: _float_array, final_transmittance: _float_array,
                            last_contributor: _int_array, out_rgb: _float_array, out_depth: _float_array,
                            grad_rgb: _float_array, grad_alpha: _float_array, grad_depth: _float_array,
                            grads: _float_array):
    """One thread per tile of the band that starts at `first_tile`; `grads` is this worker's [N, 10] buffer."""
    _composite_tile_backward(first_tile + wp.tid(), tiles_x, width, height, tile_ranges, gaussian_ids, pair_masks,
                             records, background, final_transmittance, last_contributor, out_rgb, out_depth,
                             grad_rgb, grad_alpha, grad_depth, grads)


# The host side: pack the records, allocate outputs and gradient buffers, launch one Warp thread per tile through
# the banded CPU launcher (compute/runtime.py).

_flat = flat_view  # the kernels take every array as a flat run of elements

# The records packed, and the workers' gradient rows summed and split back into the five gradients, by C++ loops over
# ROWS_PER_THREAD rows a Warp thread (torch's cat and the sums and copies of slices took 3 ms a step at 100k).
ROWS_PER_THREAD = 256


@wp.func_native(read_snippet(__package__, "cpu_simd_rows_pack.cpp", {"ROWS": ROWS_PER_THREAD}))
def _pack_rows(block: int, n: int, means2d: _float_array, conics: _float_array, opacities: _float_array,
               colors: _float_array, depths: _float_array, records: _float_array): ...


@wp.func_native(read_snippet(__package__, "cpu_simd_rows_unpack.cpp", {"ROWS": ROWS_PER_THREAD}))
def _unpack_rows(block: int, n: int, buffers: wp.array(dtype=wp.int64), workers: int, grad_means2d: _float_array,
                 grad_conics: _float_array, grad_opacities: _float_array, grad_colors: _float_array,
                 grad_depths: _float_array): ...


@wp.kernel
def pack_records_simd(first_block: int, n: int, means2d: _float_array, conics: _float_array,
                      opacities: _float_array, colors: _float_array, depths: _float_array, records: _float_array):
    """One thread per ROWS_PER_THREAD rows."""
    _pack_rows(first_block + wp.tid(), n, means2d, conics, opacities, colors, depths, records)


@wp.kernel
def sum_gradient_rows_simd(first_block: int, n: int, buffers: wp.array(dtype=wp.int64), workers: int,
                           grad_means2d: _float_array, grad_conics: _float_array, grad_opacities: _float_array,
                           grad_colors: _float_array, grad_depths: _float_array):
    """One thread per ROWS_PER_THREAD rows."""
    _unpack_rows(first_block + wp.tid(), n, buffers, workers, grad_means2d, grad_conics, grad_opacities,
                 grad_colors, grad_depths)


def pack_records(means2d, conics, opacities, colors, depths) -> torch.Tensor:
    """[N, 10] rows (mean x, y, conic a, b, c, opacity, r, g, b, depth): one cache line per list entry. The inputs
    are contiguous float32 on the CPU."""
    n = means2d.shape[0]
    records = torch.empty(n, RECORD_WIDTH)
    run_ranges(pack_records_simd, -(-n // ROWS_PER_THREAD), records.device,
               [n, *(_flat(t) for t in (means2d, conics, opacities, colors, depths, records))], 16)
    return records


def forward(records: torch.Tensor, background: torch.Tensor, bins: TileBins, width: int, height: int,
            with_median: bool = False):
    """-> rgb [H, W, 3], final transmittance [H, W], accumulated depth [H, W], last contributor [H, W] int32 (list
    position + 1 within the pixel's tile), contributed [N] bool, median Gaussian [H, W] int32 (-1 where none; None
    without with_median)."""
    n = records.shape[0]
    rgb = torch.empty(height, width, 3)
    transmittance = torch.empty(height, width)
    depth = torch.empty(height, width)
    last = torch.empty(height, width, dtype=torch.int32)
    contributed = torch.zeros(n, dtype=torch.bool)
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
    buffers = _zeroed_rows(n, workers)
    arguments = [bins.tiles_x, width, height] + [_flat(t) for t in (
        bins.tile_ranges, bins.gaussian_ids, bins.pair_masks, records, background, transmittance, last, rgb, depth,
        grad_rgb, grad_alpha, grad_depth)]
    per_worker = [_flat(b) for b in buffers]
    run_bands(composite_backward_simd, lambda worker, first_tile: [first_tile] + arguments + [per_worker[worker]],
              num_tiles, bins.tile_ranges, records.device, workers, threads_per_tile=1)
    grads = (torch.empty(n, 2), torch.empty(n, 3), torch.empty(n), torch.empty(n, 3), torch.empty(n))
    addresses = np.array([b.data_ptr() for b in buffers], dtype=np.int64)
    run_ranges(sum_gradient_rows_simd, -(-n // ROWS_PER_THREAD), records.device,
               [n, numpy_view(addresses), workers, *(_flat(g) for g in grads)], 16)
    with _spare_lock:  # zeroed by the sum: the next backward of as many Gaussians takes them
        _spare_rows[:] = [b for b in _spare_rows if b.shape[0] == n] + buffers
    return grads


# The workers' gradient rows, kept from one backward to the next (a step's backward would otherwise allocate and
# zero them: 8 MB at 100,000 Gaussians on two workers); only those of the last count of Gaussians are kept.
_spare_rows: list[torch.Tensor] = []
_spare_lock = threading.Lock()


def _zeroed_rows(n: int, workers: int) -> list[torch.Tensor]:
    """`workers` zeroed [n, RECORD_WIDTH] buffers, the spare ones first."""
    with _spare_lock:
        fitting = [b for b in _spare_rows if b.shape[0] == n]
        taken, _spare_rows[:] = fitting[:workers], fitting[workers:]
    return taken + [torch.zeros(n, RECORD_WIDTH) for _ in range(workers - len(taken))]
