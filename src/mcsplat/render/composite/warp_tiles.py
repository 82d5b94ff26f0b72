"""Compositing kernels in the shape that makes GPUs fast: the kernels CUDA runs (warp_scalar.py keeps the scalar ones).

The arithmetic per pixel is that of warp_scalar.py (its docstring has the formulas): both call warp_pixel.py's
functions. What differs is how a block of threads shares the work of a tile, as gsplat and gswarp do it:

forward    one block of 256 threads per 16x16 tile, a thread per pixel. The tile's list is walked in batches of 256
           pairs: each thread loads one pair (the Gaussian's id, its block mask and its ten numbers) into shared
           memory, and then every pixel of the tile reads the batch from there instead of each pixel fetching every
           Gaussian from global memory. Before each batch the block counts its finished pixels (past the last
           contributor, or outside the image) and stops when all are; a finished pixel still helps to load.
backward   one block of 32 threads (one warp) per two rows of a tile, walking the list back to front from the
           block's last contributor in batches of 32 pairs loaded the same way. Per Gaussian, the block's 32 pixels
           sum their ten gradient terms across the warp (a tile reduction, shuffles on CUDA) and one thread adds the
           sum to the Gaussian's gradient row: one atomic add per warp and term instead of one per pixel. A Gaussian
           whose block mask misses the warp's row of 4x4 blocks is skipped by the whole warp at once.

Gradients land in one [N, 10] buffer (means2d 2, conics 3, opacity 1, colour 3, depth 1) that the caller slices.

Both kernels use only Warp's tile operations for the block-wide work, so they also run on the CPU, where Warp (with
`wp.config.enable_cpu_blocks`) executes a block's threads as cooperative fibers: the tests check them there against
the dense reference renderer, float32 and float64, forward and every gradient. Until a GPU run is recorded in
benchmarks/README.md ("GPU"), read them as checked on CPU fibers and compiled for sm_90 only.
"""

import functools
from typing import Any

import warp as wp

from ..constants import ALPHA_MIN, BLOCK_SIZE, MEDIAN_TRANSMITTANCE, PIXELS_PER_TILE, TILE_SIZE, TRANSMITTANCE_MIN
from .warp_pixel import (RECORD_WIDTH, IntArray1, IntArray2, array_types, pixel_functions, pixel_in_tile,
                         record_type, vector_type)

FORWARD_BLOCK = PIXELS_PER_TILE          # threads per forward block: one per pixel of a tile
BACKWARD_BLOCK = 32                      # threads per backward block: one warp, two rows of a tile
BACKWARD_BLOCKS_PER_TILE = PIXELS_PER_TILE // BACKWARD_BLOCK
GRADIENT_WIDTH = RECORD_WIDTH            # the columns of the gradient buffer
# Column ranges of the gradient buffer, per parameter (start, stop).
GRADIENT_COLUMNS = {"means2d": (0, 2), "conics": (2, 5), "opacities": (5, 6), "colors": (6, 9), "depths": (9, 10)}


@functools.lru_cache(maxsize=None)
def _record_reader(dtype):
    """A Warp function reading Gaussian g's ten numbers into a record (both kernels load their batches with it)."""
    record = record_type(dtype)

    @wp.func
    def gaussian_record(g: int, means2d: wp.array2d(dtype=Any), conics: wp.array2d(dtype=Any),
                        opacities: wp.array(dtype=Any), colors: wp.array2d(dtype=Any), depths: wp.array(dtype=Any)):
        return record(means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g],
                      colors[g, 0], colors[g, 1], colors[g, 2], depths[g])

    return gaussian_record


@functools.lru_cache(maxsize=None)
def forward_kernel(dtype, with_median: bool = False):
    """The forward kernel for wp.float32 or wp.float64; `with_median` also writes each pixel's median Gaussian."""
    vec3 = vector_type(3, dtype)
    record = record_type(dtype)
    gaussian_record = _record_reader(dtype)
    pixel = pixel_functions(dtype)
    Array1, Array2, Array3 = array_types(dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def composite_forward_tiled(tiles_x: int, width: int, height: int, tile_ranges: IntArray2,
                                gaussian_ids: IntArray1, pair_masks: IntArray1, means2d: Array2, conics: Array2,
                                opacities: Array1, colors: Array2, depths: Array1, background: Array1,
                                out_rgb: Array3, out_transmittance: Array2, out_depth: Array2, out_last: IntArray2,
                                contributed: IntArray1, out_median: IntArray2):
        tile, lane = wp.tid()
        px, py, block_bit = pixel_in_tile(tile, lane, tiles_x)
        inside = px < width and py < height
        pix_x, pix_y = pixel.centre(px, py)
        start = tile_ranges[tile, 0]
        end = tile_ranges[tile, 1]

        batch_ids = wp.tile_zeros(shape=FORWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch_masks = wp.tile_zeros(shape=FORWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch = wp.tile_zeros(shape=FORWARD_BLOCK, dtype=record, storage="shared")

        transmittance = dtype(1.0)
        rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        depth = dtype(0.0)
        median = int(-1)
        last = int(0)
        done = not inside
        for batch_start in range(start, end, FORWARD_BLOCK):
            # Block-uniform: every thread sees the same count (it also orders this batch's loads after the last
            # batch's reads).
            finished = wp.tile_sum(wp.tile(wp.where(done, 1, 0)))
            if wp.tile_extract(finished, 0) == FORWARD_BLOCK:
                break
            k = batch_start + lane
            loads = k < end
            g = int(0)
            mask = int(0)
            numbers = record()
            if loads:
                g = gaussian_ids[k]
                mask = pair_masks[k]
                numbers = gaussian_record(g, means2d, conics, opacities, colors, depths)
            wp.tile_scatter_masked(batch_ids, lane, g, loads)
            wp.tile_scatter_masked(batch_masks, lane, mask, loads)
            wp.tile_scatter_masked(batch, lane, numbers, loads)  # each call ends with a barrier
            if not done:
                for i in range(wp.min(FORWARD_BLOCK, end - batch_start)):
                    if (wp.tile_extract(batch_masks, i) & block_bit) == 0:
                        continue
                    gaussian = wp.tile_extract(batch, i)
                    alpha = pixel.alpha(gaussian[0], gaussian[1], gaussian[2], gaussian[3], gaussian[4], gaussian[5],
                                        pix_x, pix_y)
                    if alpha < dtype(ALPHA_MIN):
                        continue
                    next_transmittance = transmittance * (dtype(1.0) - alpha)
                    if next_transmittance < dtype(TRANSMITTANCE_MIN):
                        done = True
                        break
                    weight = alpha * transmittance
                    rgb = rgb + weight * vec3(gaussian[6], gaussian[7], gaussian[8])
                    depth = depth + weight * gaussian[9]
                    gid = wp.tile_extract(batch_ids, i)
                    if wp.static(with_median):
                        if transmittance > dtype(MEDIAN_TRANSMITTANCE):
                            median = gid
                    transmittance = next_transmittance
                    last = batch_start + i - start + 1
                    contributed[gid] = 1

        if inside:
            pixel.write(px, py, rgb, transmittance, depth, last, background, out_rgb, out_transmittance, out_depth,
                        out_last)
            if wp.static(with_median):
                out_median[py, px] = median

    composite_forward_tiled.launch_block_dim = FORWARD_BLOCK  # compute/compile.py builds it for this block size
    return composite_forward_tiled


@functools.lru_cache(maxsize=None)
def backward_kernel(dtype, skip_unused: bool = True):
    """The backward kernel for wp.float32 or wp.float64 (gradients into an [N] array of 10-vectors). With
    `skip_unused` the warp first asks whether any of its pixels uses the Gaussian (a cheap one-value reduction) and
    skips the ten-term sum and the atomics when none does, as gsplat does with a ballot; without it every pair that
    passes the mask test is summed (fewer instructions where nearly every pair is used)."""
    vec3 = vector_type(3, dtype)
    record = record_type(dtype)
    gaussian_record = _record_reader(dtype)
    pixel = pixel_functions(dtype)
    Array1, Array2, Array3 = array_types(dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def composite_backward_tiled(tiles_x: int, width: int, height: int, tile_ranges: IntArray2,
                                 gaussian_ids: IntArray1, pair_masks: IntArray1, means2d: Array2, conics: Array2,
                                 opacities: Array1, colors: Array2, depths: Array1, background: Array1,
                                 final_transmittance: Array2, last_contributor: IntArray2, grad_rgb: Array3,
                                 grad_alpha: Array2, grad_depth: Array2, grads: wp.array(dtype=record)):
        block, lane = wp.tid()
        tile = block / BACKWARD_BLOCKS_PER_TILE
        local = (block % BACKWARD_BLOCKS_PER_TILE) * BACKWARD_BLOCK + lane
        px, py, block_bit = pixel_in_tile(tile, local, tiles_x)
        # The warp's two pixel rows lie in one row of 4x4 blocks: a pair whose mask misses that row is skipped by
        # all of its threads together.
        row_blocks = 0xF << ((local / TILE_SIZE / BLOCK_SIZE) * BLOCK_SIZE)
        pix_x, pix_y = pixel.centre(px, py)
        start = tile_ranges[tile, 0]
        last, upstream = pixel.upstream(px, py, width, height, final_transmittance, last_contributor, grad_rgb,
                                        grad_alpha, grad_depth, background)
        block_last = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)

        batch_ids = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch_masks = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=record, storage="shared")

        walk = pixel.start_walk(upstream)
        for batch_end in range(block_last, 0, -BACKWARD_BLOCK):
            batch_start = wp.max(0, batch_end - BACKWARD_BLOCK)
            # A barrier first: no thread may overwrite the batch while another still reads the last one.
            wp.tile_scatter_masked(batch_ids, 0, 0, False)
            loads = batch_start + lane < batch_end
            g = int(0)
            mask = int(0)
            numbers = record()
            if loads:
                k = start + batch_start + lane
                g = gaussian_ids[k]
                mask = pair_masks[k]
                numbers = gaussian_record(g, means2d, conics, opacities, colors, depths)
            wp.tile_scatter_masked(batch_ids, lane, g, loads)
            wp.tile_scatter_masked(batch_masks, lane, mask, loads)
            wp.tile_scatter_masked(batch, lane, numbers, loads)
            for i in range(batch_end - batch_start - 1, -1, -1):
                mask = wp.tile_extract(batch_masks, i)
                if (mask & row_blocks) == 0:  # block-uniform: no pixel of the warp can use this pair
                    continue
                gaussian = wp.tile_extract(batch, i)
                gid = wp.tile_extract(batch_ids, i)
                dx, dy, power, gauss, raw_alpha, alpha = pixel.falloff(gaussian[0], gaussian[1], gaussian[2],
                                                                       gaussian[3], gaussian[4], gaussian[5], pix_x,
                                                                       pix_y)
                used = batch_start + i < last and (mask & block_bit) != 0 and pixel.passes(power, alpha)
                terms = record()  # this pixel's ten terms, zero where it does not use the Gaussian
                if used:
                    color = vec3(gaussian[6], gaussian[7], gaussian[8])
                    walk, terms = pixel.step_back(walk, upstream, alpha, raw_alpha, gauss, color, gaussian[9], dx,
                                                  dy, gaussian[2], gaussian[3], gaussian[4])
                if wp.static(skip_unused):
                    if wp.tile_extract(wp.tile_max(wp.tile(wp.where(used, 1, 0))), 0) == 0:
                        continue
                # Summed over the block's threads; the sum's owner thread adds it (no barrier either way).
                wp.tile_atomic_add(grads, wp.tile_sum(wp.tile(terms, preserve_type=True)), gid)

    composite_backward_tiled.launch_block_dim = BACKWARD_BLOCK
    return composite_backward_tiled
