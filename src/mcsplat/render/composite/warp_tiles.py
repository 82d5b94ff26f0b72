"""Compositing kernels in the shape that makes GPUs fast: the kernels CUDA runs (warp_scalar.py keeps the scalar ones).

The arithmetic per pixel is that of warp_scalar.py (its docstring has the formulas); what differs is how a block of
threads shares the work of a tile, as gsplat and gswarp do it:

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

from __future__ import annotations

import functools
from typing import Any

import warp as wp

from ..constants import (ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, MEDIAN_TRANSMITTANCE, PIXELS_PER_TILE, POWER_SKIP,
                        TILE_SIZE, TRANSMITTANCE_MIN)

FORWARD_BLOCK = PIXELS_PER_TILE          # threads per forward block: one per pixel of a tile
BACKWARD_BLOCK = 32                      # threads per backward block: one warp, two rows of a tile
BACKWARD_BLOCKS_PER_TILE = PIXELS_PER_TILE // BACKWARD_BLOCK
GRADIENT_WIDTH = 10                      # the columns of the gradient buffer
# Column ranges of the gradient buffer, per parameter (start, stop).
GRADIENT_COLUMNS = {"means2d": (0, 2), "conics": (2, 5), "opacities": (5, 6), "colors": (6, 9), "depths": (9, 10)}


def record_type(dtype):
    """A Gaussian's ten numbers as they sit in shared memory: mean x, y; conic a, b, c; opacity; colour; depth."""
    return _vector(GRADIENT_WIDTH, dtype)


@functools.lru_cache(maxsize=None)
def _vector(length: int, dtype):
    return wp.types.vector(length, dtype)


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


@wp.func
def _pixel_in_tile(tile: int, local: int, tiles_x: int):
    """(pixel x, pixel y, bit of the pixel's 4x4 block) of pixel `local` (row-major) of `tile`."""
    px = (tile % tiles_x) * TILE_SIZE + local % TILE_SIZE
    py = (tile / tiles_x) * TILE_SIZE + local / TILE_SIZE
    block_bit = 1 << ((local / TILE_SIZE / BLOCK_SIZE) * BLOCK_SIZE + (local % TILE_SIZE) / BLOCK_SIZE)
    return px, py, block_bit


@functools.lru_cache(maxsize=None)
def forward_kernel(dtype, with_median: bool = False):
    """The forward kernel for wp.float32 or wp.float64; `with_median` also writes each pixel's median Gaussian."""
    vec3 = wp.types.vector(3, dtype)
    record = record_type(dtype)
    gaussian_record = _record_reader(dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def composite_forward_tiled(
        tiles_x: int, width: int, height: int,
        tile_ranges: wp.array2d(dtype=wp.int32), gaussian_ids: wp.array(dtype=wp.int32),
        pair_masks: wp.array(dtype=wp.int32),
        means2d: wp.array2d(dtype=dtype), conics: wp.array2d(dtype=dtype), opacities: wp.array(dtype=dtype),
        colors: wp.array2d(dtype=dtype), depths: wp.array(dtype=dtype), background: wp.array(dtype=dtype),
        out_rgb: wp.array3d(dtype=dtype), out_transmittance: wp.array2d(dtype=dtype),
        out_depth: wp.array2d(dtype=dtype), out_last: wp.array2d(dtype=wp.int32),
        contributed: wp.array(dtype=wp.int32), out_median: wp.array2d(dtype=wp.int32),
    ):
        tile, lane = wp.tid()
        px, py, block_bit = _pixel_in_tile(tile, lane, tiles_x)
        inside = px < width and py < height
        pix_x = dtype(px) + dtype(0.5)
        pix_y = dtype(py) + dtype(0.5)
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
                    dx = gaussian[0] - pix_x
                    dy = gaussian[1] - pix_y
                    power = dtype(-0.5) * (gaussian[2] * dx * dx + gaussian[4] * dy * dy) - gaussian[3] * dx * dy
                    if power > dtype(0.0) or power < dtype(POWER_SKIP):
                        continue
                    alpha = wp.min(dtype(ALPHA_MAX), gaussian[5] * wp.exp(power))
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
            for ch in range(3):
                out_rgb[py, px, ch] = rgb[ch] + transmittance * background[ch]
            out_transmittance[py, px] = transmittance
            out_depth[py, px] = depth
            out_last[py, px] = last
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
    vec3 = wp.types.vector(3, dtype)
    record = record_type(dtype)
    gaussian_record = _record_reader(dtype)

    @wp.kernel(module="unique", enable_backward=False)
    def composite_backward_tiled(
        tiles_x: int, width: int, height: int,
        tile_ranges: wp.array2d(dtype=wp.int32), gaussian_ids: wp.array(dtype=wp.int32),
        pair_masks: wp.array(dtype=wp.int32),
        means2d: wp.array2d(dtype=dtype), conics: wp.array2d(dtype=dtype), opacities: wp.array(dtype=dtype),
        colors: wp.array2d(dtype=dtype), depths: wp.array(dtype=dtype), background: wp.array(dtype=dtype),
        final_transmittance: wp.array2d(dtype=dtype), last_contributor: wp.array2d(dtype=wp.int32),
        grad_rgb: wp.array3d(dtype=dtype), grad_alpha: wp.array2d(dtype=dtype), grad_depth: wp.array2d(dtype=dtype),
        grads: wp.array(dtype=record),
    ):
        block, lane = wp.tid()
        tile = block / BACKWARD_BLOCKS_PER_TILE
        local = (block % BACKWARD_BLOCKS_PER_TILE) * BACKWARD_BLOCK + lane
        px, py, block_bit = _pixel_in_tile(tile, local, tiles_x)
        # The warp's two pixel rows lie in one row of 4x4 blocks: a pair whose mask misses that row is skipped by
        # all of its threads together.
        row_blocks = 0xF << ((local / TILE_SIZE / BLOCK_SIZE) * BLOCK_SIZE)
        inside = px < width and py < height
        qx = wp.min(px, width - 1)
        qy = wp.min(py, height - 1)
        pix_x = dtype(px) + dtype(0.5)
        pix_y = dtype(py) + dtype(0.5)
        start = tile_ranges[tile, 0]
        last = int(0)
        if inside:
            last = last_contributor[qy, qx]
        block_last = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)

        t_final = final_transmittance[qy, qx]
        dl_drgb = vec3(grad_rgb[qy, qx, 0], grad_rgb[qy, qx, 1], grad_rgb[qy, qx, 2])
        dl_ddepth = grad_depth[qy, qx]
        dl_dalpha_out = grad_alpha[qy, qx]
        bg = vec3(background[0], background[1], background[2])
        bg_term = wp.dot(bg, dl_drgb)

        batch_ids = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch_masks = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=wp.int32, storage="shared")
        batch = wp.tile_zeros(shape=BACKWARD_BLOCK, dtype=record, storage="shared")

        transmittance = t_final
        behind_rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))  # colour composited behind the current Gaussian
        behind_depth = dtype(0.0)
        next_alpha = dtype(0.0)
        next_rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        next_depth = dtype(0.0)
        zero = dtype(0.0)
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
                dx = gaussian[0] - pix_x
                dy = gaussian[1] - pix_y
                ca = gaussian[2]
                cb = gaussian[3]
                cc = gaussian[4]
                power = dtype(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                gauss = wp.exp(wp.min(power, zero))
                raw_alpha = gaussian[5] * gauss
                alpha = wp.min(dtype(ALPHA_MAX), raw_alpha)
                used = (batch_start + i < last and (mask & block_bit) != 0 and power <= zero
                        and power >= dtype(POWER_SKIP) and alpha >= dtype(ALPHA_MIN))
                terms = record()  # this pixel's ten terms, zero where it does not use the Gaussian
                if used:
                    one_minus_alpha = dtype(1.0) - alpha
                    transmittance = transmittance / one_minus_alpha
                    weight = alpha * transmittance
                    color = vec3(gaussian[6], gaussian[7], gaussian[8])
                    depth = gaussian[9]
                    behind_rgb = next_alpha * next_rgb + (dtype(1.0) - next_alpha) * behind_rgb
                    behind_depth = next_alpha * next_depth + (dtype(1.0) - next_alpha) * behind_depth
                    next_alpha = alpha
                    next_rgb = color
                    next_depth = depth

                    dl_dalpha = transmittance * (wp.dot(color - behind_rgb, dl_drgb)
                                                 + (depth - behind_depth) * dl_ddepth)
                    # The background and the output alpha (1 - T_final) both depend on alpha through T_final.
                    dl_dalpha = dl_dalpha + (t_final / one_minus_alpha) * (dl_dalpha_out - bg_term)
                    d_opacity = zero
                    dl_dpower = zero
                    if raw_alpha <= dtype(ALPHA_MAX):  # clamped: alpha no longer depends on opacity or position
                        d_opacity = gauss * dl_dalpha
                        dl_dpower = raw_alpha * dl_dalpha
                    terms = record(-dl_dpower * (ca * dx + cb * dy), -dl_dpower * (cb * dx + cc * dy),
                                   dtype(-0.5) * dl_dpower * dx * dx, -dl_dpower * dx * dy,
                                   dtype(-0.5) * dl_dpower * dy * dy, d_opacity,
                                   weight * dl_drgb[0], weight * dl_drgb[1], weight * dl_drgb[2], weight * dl_ddepth)
                if wp.static(skip_unused):
                    if wp.tile_extract(wp.tile_max(wp.tile(wp.where(used, 1, 0))), 0) == 0:
                        continue
                # Summed over the block's threads; the sum's owner thread adds it (no barrier either way).
                wp.tile_atomic_add(grads, wp.tile_sum(wp.tile(terms, preserve_type=True)), gid)

    composite_backward_tiled.launch_block_dim = BACKWARD_BLOCK
    return composite_backward_tiled
