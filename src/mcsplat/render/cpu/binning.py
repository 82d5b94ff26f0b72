"""The binning's per-Gaussian work for the CPU as C++ loops (`wp.func_native`): the same pairs, masks and lists as the
Warp kernels of render/binning.py (which CUDA runs, and the CPU when another choice of kernels is made), several
times faster on the CPU because a thread walks a range of Gaussians with plain integer arithmetic (a block mask is
one multiplication) instead of a Warp thread per Gaussian.

Four kernels, in the order binning.bin_gaussians runs them:
- count_pairs_cpu: each Gaussian's non-empty pairs, one thread per range of Gaussians;
- slot_offsets_cpu: one thread: each Gaussian's first slot, the Gaussians taken front to back, and the total;
- write_pairs_cpu: each pair's tile key and (block mask << 32 | Gaussian) value at its slot, one thread per range;
- split_pairs_cpu: one thread, after the sort by tile: the Gaussian and the mask of each pair, each tile's range.
"""

from __future__ import annotations

import warp as wp

from ..constants import ALL_BLOCKS, BLOCK_SIZE, TILE_SIZE

_int_array = wp.array(dtype=wp.int32)
_long_array = wp.array(dtype=wp.int64)
_float_array = wp.array(dtype=wp.float32)

# The tiles [x0, x1) x [y0, y1) of Gaussian i's non-empty pairs and its pixel span, as binning._pair_tiles: the first
# and last pixel whose centre lies within mean -+ extent (bounds clamped to 1e9 before the conversion to int), the
# tiles of its rectangle that hold a pixel of the span.
_PAIR_TILES = f"""
    const int* tile_min_ = (const int*)tile_min.data;
    const int* tile_max_ = (const int*)tile_max.data;
    const float* means2d_ = (const float*)means2d.data;
    const float* extent_ = (const float*)alpha_extent.data;
    auto clamped = [](float x) -> float {{ return x < -1.0e9f ? -1.0e9f : (x > 1.0e9f ? 1.0e9f : x); }};
    auto pair_tiles = [&](int i, int* span, int* rect) {{
        rect[0] = tile_min_[2 * i]; rect[1] = tile_max_[2 * i];
        rect[2] = tile_min_[2 * i + 1]; rect[3] = tile_max_[2 * i + 1];
        if (!use_masks) return;
        for (int axis = 0; axis < 2; ++axis) {{
            const float mean = means2d_[2 * i + axis], extent = extent_[2 * i + axis];
            const int first = (int)__builtin_ceilf(clamped(mean - extent - 0.5f));
            const int last = (int)__builtin_floorf(clamped(mean + extent - 0.5f));
            span[2 * axis] = first; span[2 * axis + 1] = last;
            int* lo = rect + 2 * axis;
            int* hi = rect + 2 * axis + 1;
            if (last < first || last < 0) {{ *hi = *lo; continue; }}
            const int a = (first > 0 ? first : 0) / {TILE_SIZE}, b = last / {TILE_SIZE} + 1;
            if (a > *lo) *lo = a;
            if (b < *hi) *hi = b;
        }}
    }};
"""

_COUNT = _PAIR_TILES + """
    int* counts_ = (int*)counts.data;
    for (int i = begin; i < end; ++i) {
        int span[4], rect[4];
        pair_tiles(i, span, rect);
        const int w = rect[1] - rect[0], h = rect[3] - rect[2];
        counts_[i] = (w > 0 ? w : 0) * (h > 0 ? h : 0);
    }
"""

_SLOTS = """
    const int* order_ = (const int*)order.data;
    const int* counts_ = (const int*)counts.data;
    int* offsets_ = (int*)offsets.data;
    long long slot = 0;
    for (int k = 0; k < n; ++k) {
        const int g = order_[k];
        offsets_[g] = (int)slot;
        slot += counts_[g];
    }
    ((long long*)total.data)[0] = slot;
"""

_WRITE = _PAIR_TILES + f"""
    const int* offsets_ = (const int*)offsets.data;
    int* tiles_ = (int*)tiles.data;
    long long* pairs_ = (long long*)pairs.data;
    for (int i = begin; i < end; ++i) {{
        int span[4], rect[4];
        pair_tiles(i, span, rect);
        int slot = offsets_[i];
        for (int ty = rect[2]; ty < rect[3]; ++ty) {{
            // The rows of 4x4 blocks of tile row ty that the span reaches, as a column of 4-bit groups.
            int column = 0xffff;
            if (use_masks) {{
                const int fy = span[2] - ty * {TILE_SIZE}, ly = span[3] - ty * {TILE_SIZE};
                const int bfy = (fy > 0 ? fy : 0) / {BLOCK_SIZE};
                const int bly = (ly < {TILE_SIZE - 1} ? ly : {TILE_SIZE - 1}) / {BLOCK_SIZE};
                column = ((1 << ({BLOCK_SIZE} * (bly + 1))) - (1 << ({BLOCK_SIZE} * bfy))) / 15;
            }}
            for (int tx = rect[0]; tx < rect[1]; ++tx) {{
                int mask = {ALL_BLOCKS};
                if (use_masks) {{
                    const int fx = span[0] - tx * {TILE_SIZE}, lx = span[1] - tx * {TILE_SIZE};
                    const int bfx = (fx > 0 ? fx : 0) / {BLOCK_SIZE};
                    const int blx = (lx < {TILE_SIZE - 1} ? lx : {TILE_SIZE - 1}) / {BLOCK_SIZE};
                    mask = ((1 << (blx + 1)) - (1 << bfx)) * column;  // the row of blocks, in every row of the column
                }}
                tiles_[slot] = ty * tiles_x + tx;
                pairs_[slot] = ((long long)mask << 32) | (long long)i;
                ++slot;
            }}
        }}
    }}
"""

_SPLIT = """
    const int* tiles_ = (const int*)tiles.data;
    const long long* pairs_ = (const long long*)pairs.data;
    int* ids_ = (int*)gaussian_ids.data;
    int* masks_ = (int*)pair_masks.data;
    int* ranges_ = (int*)tile_ranges.data;
    for (int k = 0; k < total; ++k) {
        ids_[k] = (int)(pairs_[k] & 0xffffffffLL);
        masks_[k] = (int)(pairs_[k] >> 32);
    }
    int k = 0;
    for (int t = 0; t < num_tiles; ++t) {  // the pairs are sorted by tile; an empty tile's range is empty
        ranges_[2 * t] = k;
        while (k < total && tiles_[k] == t) ++k;
        ranges_[2 * t + 1] = k;
    }
"""


@wp.func_native(_COUNT)
def _count_range(begin: int, end: int, tile_min: _int_array, tile_max: _int_array, means2d: _float_array,
                 alpha_extent: _float_array, use_masks: int, counts: _int_array): ...


@wp.func_native(_SLOTS)
def _slots(n: int, order: _int_array, counts: _int_array, offsets: _int_array, total: _long_array): ...


@wp.func_native(_WRITE)
def _write_range(begin: int, end: int, tile_min: _int_array, tile_max: _int_array, means2d: _float_array,
                 alpha_extent: _float_array, use_masks: int, tiles_x: int, offsets: _int_array, tiles: _int_array,
                 pairs: _long_array): ...


@wp.func_native(_SPLIT)
def _split(total: int, num_tiles: int, tiles: _int_array, pairs: _long_array, gaussian_ids: _int_array,
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
def slot_offsets_cpu(n: int, order: _int_array, counts: _int_array, offsets: _int_array, total: _long_array):
    """One thread: offsets[g] = the pairs of the Gaussians in front of g (order: front to back); total[0] = all."""
    _slots(n, order, counts, offsets, total)


@wp.kernel
def write_pairs_cpu(first_part: int, n: int, parts: int, tile_min: _int_array, tile_max: _int_array,
                    means2d: _float_array, alpha_extent: _float_array, use_masks: int, tiles_x: int,
                    offsets: _int_array, tiles: _int_array, pairs: _long_array):
    """Part p of `parts` writes the pairs of Gaussians [n p / parts, n (p + 1) / parts) at their slots."""
    p = first_part + wp.tid()
    _write_range(n * p // parts, n * (p + 1) // parts, tile_min, tile_max, means2d, alpha_extent, use_masks,
                 tiles_x, offsets, tiles, pairs)


@wp.kernel
def split_pairs_cpu(total: int, num_tiles: int, tiles: _int_array, pairs: _long_array, gaussian_ids: _int_array,
                    pair_masks: _int_array, tile_ranges: _int_array):
    """One thread: the sorted pairs split into Gaussians and masks, and each tile's [start, end)."""
    _split(total, num_tiles, tiles, pairs, gaussian_ids, pair_masks, tile_ranges)
