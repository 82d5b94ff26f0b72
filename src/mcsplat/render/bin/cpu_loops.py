"""The binning's per-Gaussian work for the CPU as C++ loops (`wp.func_native`): the same pairs, masks and lists as the
Warp kernels of warp_kernels.py (which CUDA runs, and the CPU when another choice of kernels is made), several
times faster on the CPU because a thread walks a range of Gaussians with plain integer arithmetic (a block mask is
one multiplication) instead of a Warp thread per Gaussian.

Four kernels, in the order warp_kernels.bin_gaussians runs them:
- count_pairs_cpu: each Gaussian's non-empty pairs, one thread per range of Gaussians;
- depth_slots_cpu: one thread: the Gaussians front to back (a radix sort of their depths' bits), then each one's
  first slot, and the total;
- write_pairs_cpu: each pair's tile key and (block mask << 32 | Gaussian) value at its slot, one thread per range;
- sort_split_cpu: one thread: the pairs sorted by tile (a counting sort, stable) into the Gaussian and the mask of
  each pair, and each tile's range.
The two sorts are the lists' order of Warp's radix sorts (stable, by the same keys), in a third of their time: those
take 16-bit digits (two passes of 65,536 counts for the depths) and copy a one-pass result back.
"""

from __future__ import annotations

import warp as wp

from ...compute.cpp_snippets import read_snippet
from ..constants import ALL_BLOCKS, BLOCK_SIZE, TILE_SIZE

_int_array = wp.array(dtype=wp.int32)
_long_array = wp.array(dtype=wp.int64)
_float_array = wp.array(dtype=wp.float32)

# The C++ is in cpu_loops_*.cpp, one file per function; cpu_loops_pair_tiles.h, which the count and the write share,
# finds the tiles [x0, x1) x [y0, y1) of Gaussian i's non-empty pairs and its pixel span, as warp_kernels._pair_tiles:
# the first and last pixel whose centre lies within mean -+ extent (bounds clamped to 1e9 before the conversion to
# int), the tiles of its rectangle that hold a pixel of the span.
_PAIR_TILES = read_snippet(__package__, "cpu_loops_pair_tiles.h", {"TILE_SIZE": TILE_SIZE})

_COUNT = read_snippet(__package__, "cpu_loops_count.cpp", {"PAIR_TILES": _PAIR_TILES})

_DEPTH_SLOTS = read_snippet(__package__, "cpu_loops_order.cpp")

_WRITE = read_snippet(__package__, "cpu_loops_write.cpp", {
    "PAIR_TILES": _PAIR_TILES, "TILE_SIZE": TILE_SIZE, "TILE_LAST": TILE_SIZE - 1, "BLOCK_SIZE": BLOCK_SIZE,
    "ALL_BLOCKS": ALL_BLOCKS})

_SORT_SPLIT = read_snippet(__package__, "cpu_loops_sort_split.cpp")


@wp.func_native(_COUNT)
def _count_range(begin: int, end: int, tile_min: _int_array, tile_max: _int_array, means2d: _float_array,
                 alpha_extent: _float_array, use_masks: int, counts: _int_array): ...


@wp.func_native(_DEPTH_SLOTS)
def _depth_slots(n: int, depths: _float_array, radii: _int_array, counts: _int_array, keys: _int_array,
                 order: _int_array, offsets: _int_array, total: _long_array): ...


@wp.func_native(_WRITE)
def _write_range(begin: int, end: int, tile_min: _int_array, tile_max: _int_array, means2d: _float_array,
                 alpha_extent: _float_array, use_masks: int, tiles_x: int, offsets: _int_array, tiles: _int_array,
                 pairs: _long_array): ...


@wp.func_native(_SORT_SPLIT)
def _sort_split(total: int, num_tiles: int, tiles: _int_array, pairs: _long_array, gaussian_ids: _int_array,
                pair_masks: _int_array, tile_ranges: _int_array): ...


@wp.kernel
def count_pairs_cpu(first_part: int, n: int, parts: int, tile_min: _int_array, tile_max: _int_array,
                    means2d: _float_array, alpha_extent: _float_array, use_masks: int, counts: _int_array):
    """Part p of `parts` counts the pairs of Gaussians [n p / parts, n (p + 1) / parts) (one part per thread of the
    pool, compute.runtime.run_ranges over the parts)."""
    p = first_part + wp.tid()
    _count_range(n * p // parts, n * (p + 1) // parts, tile_min, tile_max, means2d, alpha_extent, use_masks,
                 counts)


@wp.kernel
def depth_slots_cpu(n: int, depths: _float_array, radii: _int_array, counts: _int_array, keys: _int_array,
                    order: _int_array, offsets: _int_array, total: _long_array):
    """One thread: offsets[g] = the pairs of the Gaussians in front of g (the visible ones by depth, equal depths by
    index, the others first); total[0] = all. `keys` and `order` are rooms of 2n for the sort."""
    _depth_slots(n, depths, radii, counts, keys, order, offsets, total)


@wp.kernel
def write_pairs_cpu(first_part: int, n: int, parts: int, tile_min: _int_array, tile_max: _int_array,
                    means2d: _float_array, alpha_extent: _float_array, use_masks: int, tiles_x: int,
                    offsets: _int_array, tiles: _int_array, pairs: _long_array):
    """Part p of `parts` writes the pairs of Gaussians [n p / parts, n (p + 1) / parts) at their slots."""
    p = first_part + wp.tid()
    _write_range(n * p // parts, n * (p + 1) // parts, tile_min, tile_max, means2d, alpha_extent, use_masks,
                 tiles_x, offsets, tiles, pairs)


@wp.kernel
def sort_split_cpu(total: int, num_tiles: int, tiles: _int_array, pairs: _long_array, gaussian_ids: _int_array,
                   pair_masks: _int_array, tile_ranges: _int_array):
    """One thread: the pairs as written, sorted by tile into Gaussians and masks, and each tile's [start, end)."""
    _sort_split(total, num_tiles, tiles, pairs, gaussian_ids, pair_masks, tile_ranges)
