"""SIMD alpha compositing for the CPU: one 4x4 pixel block in 16 vector lanes, forward and hand-written backward.

Same rules and outputs as the scalar kernels of render/kernels.py (which stay the CUDA path, the float64 path and the
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
"""

from __future__ import annotations

import warp as wp

from ...compute.cpu_target import kernel_flags
from ..constants import (ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, MEDIAN_TRANSMITTANCE, POWER_SKIP, TILE_SIZE,
                         TRANSMITTANCE_MIN)

# The tile bodies hold a tile as 16 blocks of 16 lanes: they are written for 16x16 tiles of 4x4 blocks.
assert TILE_SIZE == 16 and BLOCK_SIZE == 4, "the SIMD tile body needs 16x16 tiles of 4x4 pixel blocks"

RECORD_WIDTH = 10
# How many list entries ahead the tile bodies ask for a record (and its gradient row): about a memory latency of work.
PREFETCH_DISTANCE = 8

# Types and helpers shared by both tile bodies. Masks are int vectors of 0 / -1 (clang's vector comparisons).
_PRELUDE = f"""
    typedef float vf __attribute__((ext_vector_type(16)));
    typedef int vi __attribute__((ext_vector_type(16)));
    typedef float vf8 __attribute__((ext_vector_type(8)));
    typedef float vf4 __attribute__((ext_vector_type(4)));
    const float alpha_min = {ALPHA_MIN!r}f, alpha_max = {ALPHA_MAX}f;
    const int PREFETCH_DISTANCE = {PREFETCH_DISTANCE};
    const float power_skip = {POWER_SKIP!r}f, transmittance_min = {TRANSMITTANCE_MIN}f;

    auto select = [](vi mask, vf a, vf b) -> vf {{ return (vf)(((vi)a & mask) | ((vi)b & ~mask)); }};
    auto any_lane = [](vi mask) -> bool {{ return __builtin_reduce_or(mask) != 0; }};
    auto all_lanes = [](vi mask) -> bool {{ return __builtin_reduce_and(mask) != 0; }};
    // Sum of the 16 lanes in a fixed tree order (the result must not depend on the compiler's choices).
    auto lane_sum = [](vf v) -> float {{
        vf8 a = v.lo + v.hi;
        vf4 b = a.lo + a.hi;
        return (b.x + b.z) + (b.y + b.w);
    }};
    // exp(x) for x in [power_skip, 0] (Cephes' expf polynomial with the 2^n exponent trick): a libm call would
    // stop the loop from vectorising. Relative error about 1e-7, and the same function serves forward and backward.
    auto exp_lanes = [](vf x) -> vf {{
        vf fx = x * 1.44269504088896341f + 0.5f;
        vi n = __builtin_convertvector(fx, vi);
        n -= (vi)(__builtin_convertvector(n, vf) > fx) & 1;  // truncation -> floor for negative values
        vf nf = __builtin_convertvector(n, vf);
        x = x - nf * 0.693359375f + nf * 2.12194440e-4f;
        vf p = 1.9875691500e-4f;
        p = p * x + 1.3981999507e-3f;
        p = p * x + 8.3334519073e-3f;
        p = p * x + 4.1665795894e-2f;
        p = p * x + 1.6666665459e-1f;
        p = p * x + 5.0000001201e-1f;
        p = p * x * x + x + 1.0f;
        return p * (vf)((n + 127) << 23);
    }};

    const int* range = (const int*)tile_ranges.data + 2 * tile;
    const int start = range[0], end = range[1];
    const int* ids = (const int*)gaussian_ids.data;
    const int* pair_masks_ = (const int*)pair_masks.data;
    const float* rows = (const float*)records.data;
    // The list's Gaussians lie anywhere in the records (and, backward, in the gradient rows): a record fetched
    // when its entry comes up costs a miss of the cache each time, so the entry PREFETCH_DISTANCE ahead is asked
    // for early (both cache lines a 40-byte row may straddle).
    auto prefetch_ahead = [&](int k, const float* gradient_rows) {{
        if (k + PREFETCH_DISTANCE >= end) return;
        const int ahead = 10 * ids[k + PREFETCH_DISTANCE];
        __builtin_prefetch(rows + ahead);
        __builtin_prefetch(rows + ahead + 9);
        if (gradient_rows) {{
            __builtin_prefetch(gradient_rows + ahead, 1);
            __builtin_prefetch(gradient_rows + ahead + 9, 1);
        }}
    }};
    const int tile_x0 = (tile % tiles_x) * {TILE_SIZE}, tile_y0 = (tile / tiles_x) * {TILE_SIZE};
    vf lane_dx, lane_dy;  // pixel-centre offsets of the 16 lanes inside a 4x4 block
    vi lane_x, lane_y;
    for (int l = 0; l < 16; ++l) {{
        lane_x[l] = l % 4; lane_y[l] = l / 4;
        lane_dx[l] = (float)(l % 4) + 0.5f; lane_dy[l] = (float)(l / 4) + 0.5f;
    }}
    int block_x0[16], block_y0[16];
    vi inside[16];  // lanes on image pixels (the last tiles may hang over the edge)
    for (int b = 0; b < 16; ++b) {{
        block_x0[b] = tile_x0 + (b % 4) * 4;
        block_y0[b] = tile_y0 + (b / 4) * 4;
        inside[b] = ((lane_x + block_x0[b]) < width) & ((lane_y + block_y0[b]) < height);
    }}
"""

# Evaluates one Gaussian (scalars mx, my, ca, cb, cc, opacity) on block b in two steps: the power, and the lanes
# where it is in [power_skip, 0]; then, only where some lane that still takes part (`taking_part`) is in range, the
# exponential, alpha and the lanes that pass the exact tests of the scalar kernel (power in range, alpha >= 1/255).
_POWER = """
            vf dx = mx - ((float)block_x0[b] + lane_dx);
            vf dy = my - ((float)block_y0[b] + lane_dy);
            vf power = -0.5f * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
            vi in_range = (power <= 0.0f) & (power >= power_skip);
"""
_ALPHA = """
            vf gauss = exp_lanes(select(in_range, power, (vf)0.0f));
            vf raw_alpha = opacity * gauss;
            vf alpha = select(raw_alpha < alpha_max, raw_alpha, (vf)alpha_max);
            vi passes = in_range & (alpha >= alpha_min);
"""


def _evaluate_block(taking_part: str) -> str:
    return _POWER + f"""
            if (!any_lane(in_range & ({taking_part}))) continue;
""" + _ALPHA


# The forward body is a template: with_median fills its MEDIAN_* marks (the training kernel gets them empty).
_FORWARD_TEMPLATE = _PRELUDE + """
    vf transmittance[16], red[16], green[16], blue[16], depth[16];
    vi last[16], done[16];
MEDIAN_DECLARE
    int active = 0;  // blocks with a pixel still compositing
    for (int b = 0; b < 16; ++b) {
        transmittance[b] = 1.0f; red[b] = 0.0f; green[b] = 0.0f; blue[b] = 0.0f; depth[b] = 0.0f;
        last[b] = 0; done[b] = ~inside[b];
        if (!all_lanes(done[b])) active |= 1 << b;
    }
    int* contributed_ = (int*)contributed.data;
    for (int k = start; k < end && active; ++k) {
        prefetch_ahead(k, nullptr);
        int blocks = pair_masks_[k] & active;
        if (!blocks) continue;
        const int g = ids[k];
        const float* row = rows + 10 * g;
        const float mx = row[0], my = row[1], ca = row[2], cb = row[3], cc = row[4], opacity = row[5];
        bool composited = false;
        while (blocks) {
            const int b = __builtin_ctz(blocks);
            blocks &= blocks - 1;
""" + _evaluate_block("~done[b]") + """
            vi use = passes & ~done[b];
            if (!any_lane(use)) continue;
            vf next_t = transmittance[b] * (1.0f - alpha);
            vi stop = use & (next_t < transmittance_min);
            done[b] |= stop;
            use &= ~stop;
            vf weight = select(use, alpha * transmittance[b], (vf)0.0f);
            red[b] += weight * row[6];
            green[b] += weight * row[7];
            blue[b] += weight * row[8];
            depth[b] += weight * row[9];
MEDIAN_UPDATE
            transmittance[b] = select(use, next_t, transmittance[b]);
            last[b] = (use & (k - start + 1)) | (~use & last[b]);
            composited = composited || any_lane(use);
            if (all_lanes(done[b])) active &= ~(1 << b);
        }
        if (composited) contributed_[g] = 1;
    }

    const float* bg = (const float*)background.data;
    float* rgb_out = (float*)out_rgb.data;
    float* t_out = (float*)out_transmittance.data;
    float* depth_out = (float*)out_depth.data;
    int* last_out = (int*)out_last.data;
    for (int b = 0; b < 16; ++b) {
        for (int l = 0; l < 16; ++l) {
            const int px = block_x0[b] + l % 4, py = block_y0[b] + l / 4;
            if (px >= width || py >= height) continue;
            const int pixel = py * width + px;
            const float t = transmittance[b][l];
            rgb_out[3 * pixel + 0] = red[b][l] + t * bg[0];
            rgb_out[3 * pixel + 1] = green[b][l] + t * bg[1];
            rgb_out[3 * pixel + 2] = blue[b][l] + t * bg[2];
            t_out[pixel] = t;
            depth_out[pixel] = depth[b][l];
            last_out[pixel] = last[b][l];
MEDIAN_STORE
        }
    }
"""

# The median Gaussian (render/kernels.py): the last one composited while the transmittance in front of it is still
# above MEDIAN_TRANSMITTANCE (-1 where none is), one vector of ids per block.
_MEDIAN_LINES = {
    "MEDIAN_DECLARE": f"""    vi median[16];
    for (int b = 0; b < 16; ++b) median[b] = -1;
    const float median_transmittance = {MEDIAN_TRANSMITTANCE}f;
    int* median_out = (int*)out_median.data;""",
    "MEDIAN_UPDATE": """            vi in_front_half = use & (transmittance[b] > median_transmittance);
            median[b] = (in_front_half & g) | (~in_front_half & median[b]);""",
    "MEDIAN_STORE": "            median_out[pixel] = median[b][l];",
}


def _forward_body(with_median: bool) -> str:
    body = _FORWARD_TEMPLATE
    for mark, lines in _MEDIAN_LINES.items():
        body = body.replace(f"{mark}\n", lines + "\n" if with_median else "")
    return body


_BACKWARD_BODY = _PRELUDE + """
    const float* bg = (const float*)background.data;
    const float* t_final = (const float*)final_transmittance.data;
    const int* last_in = (const int*)last_contributor.data;
    const float* rgb_in = (const float*)out_rgb.data;
    const float* depth_in = (const float*)out_depth.data;
    const float* g_rgb = (const float*)grad_rgb.data;
    const float* g_alpha = (const float*)grad_alpha.data;
    const float* g_depth = (const float*)grad_depth.data;
    float* grads_ = (float*)grads.data;

    // Per block: the upstream gradients, R (see the module docstring), the walk's state T and S, and the last
    // contributor of each lane; lanes off the image have last = 0 and take no part.
    vf gr[16], gg[16], gb[16], gd[16], rest[16], transmittance[16], prefix[16];
    vi last[16];
    int block_end[16];  // largest last contributor of the block
    int active = 0;
    for (int b = 0; b < 16; ++b) {
        block_end[b] = 0;
        for (int l = 0; l < 16; ++l) {
            const int px = block_x0[b] + l % 4, py = block_y0[b] + l / 4;
            if (px >= width || py >= height) {
                gr[b][l] = 0.0f; gg[b][l] = 0.0f; gb[b][l] = 0.0f; gd[b][l] = 0.0f; rest[b][l] = 0.0f;
                last[b][l] = 0;
                continue;
            }
            const int pixel = py * width + px;
            const float t = t_final[pixel];
            const float r = g_rgb[3 * pixel], g = g_rgb[3 * pixel + 1], bl = g_rgb[3 * pixel + 2];
            const float bg_term = bg[0] * r + bg[1] * g + bg[2] * bl;
            const float total = (rgb_in[3 * pixel] - t * bg[0]) * r + (rgb_in[3 * pixel + 1] - t * bg[1]) * g
                                + (rgb_in[3 * pixel + 2] - t * bg[2]) * bl + depth_in[pixel] * g_depth[pixel];
            gr[b][l] = r; gg[b][l] = g; gb[b][l] = bl; gd[b][l] = g_depth[pixel];
            rest[b][l] = total - t * (g_alpha[pixel] - bg_term);
            last[b][l] = last_in[pixel];
            if (last_in[pixel] > block_end[b]) block_end[b] = last_in[pixel];
        }
        transmittance[b] = 1.0f; prefix[b] = 0.0f;
        if (block_end[b] > 0) active |= 1 << b;
    }

    for (int k = start; k < end && active; ++k) {
        prefetch_ahead(k, grads_);
        int blocks = pair_masks_[k] & active;
        if (!blocks) continue;
        const int g = ids[k];
        const float* row = rows + 10 * g;
        const float mx = row[0], my = row[1], ca = row[2], cb = row[3], cc = row[4], opacity = row[5];
        const float cr = row[6], cg = row[7], cbl = row[8], z = row[9];
        const int index = k - start;
        vf sum_mx = 0.0f, sum_my = 0.0f, sum_ca = 0.0f, sum_cb = 0.0f, sum_cc = 0.0f, sum_op = 0.0f;
        vf sum_r = 0.0f, sum_g = 0.0f, sum_b = 0.0f, sum_z = 0.0f;
        bool touched = false;
        while (blocks) {
            const int b = __builtin_ctz(blocks);
            blocks &= blocks - 1;
            if (index + 1 >= block_end[b]) active &= ~(1 << b);  // this entry is the block's last one to visit
""" + _evaluate_block("last[b] > index") + """
            vi use = passes & (last[b] > index);
            if (!any_lane(use)) continue;
            touched = true;
            vf t = transmittance[b];
            vf weight = select(use, alpha * t, (vf)0.0f);
            sum_r += weight * gr[b];
            sum_g += weight * gg[b];
            sum_b += weight * gb[b];
            sum_z += weight * gd[b];
            vf h = cr * gr[b] + cg * gg[b] + cbl * gb[b] + z * gd[b];
            vf one_minus_alpha = 1.0f - alpha;
            prefix[b] += weight * h;
            transmittance[b] = select(use, t * one_minus_alpha, t);
            // Clamped alphas (raw alpha above 0.99) no longer depend on opacity or position.
            vi free_alpha = use & (raw_alpha <= alpha_max);
            vf dl_dalpha = select(free_alpha, t * h - (rest[b] - prefix[b]) / one_minus_alpha, (vf)0.0f);
            sum_op += gauss * dl_dalpha;
            vf dl_dpower = raw_alpha * dl_dalpha;
            sum_mx -= dl_dpower * (ca * dx + cb * dy);
            sum_my -= dl_dpower * (cb * dx + cc * dy);
            sum_ca -= 0.5f * dl_dpower * dx * dx;
            sum_cb -= dl_dpower * dx * dy;
            sum_cc -= 0.5f * dl_dpower * dy * dy;
        }
        if (!touched) continue;
        float* out = grads_ + 10 * g;
        out[0] += lane_sum(sum_mx); out[1] += lane_sum(sum_my);
        out[2] += lane_sum(sum_ca); out[3] += lane_sum(sum_cb); out[4] += lane_sum(sum_cc);
        out[5] += lane_sum(sum_op);
        out[6] += lane_sum(sum_r); out[7] += lane_sum(sum_g); out[8] += lane_sum(sum_b);
        out[9] += lane_sum(sum_z);
    }
"""

# 512-bit vectors where the CPU has them (clang otherwise splits a 16-lane vector into two 256-bit halves; on AVX2 the
# 16 lanes take two registers each, and 8-lane vectors over half-blocks measured no faster there). Fused multiply-add
# (Warp's default keeps a * b + c as two roundings) makes the kernels about 10% faster.
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512 -ffp-contract=fast")})

_int_array = wp.array(dtype=wp.int32)
_float_array = wp.array(dtype=wp.float32)


@wp.func_native(_forward_body(with_median=False))
def _composite_tile_forward(tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                            gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                            background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                            out_depth: _float_array, out_last: _int_array, contributed: _int_array): ...


@wp.func_native(_forward_body(with_median=True))
def _composite_tile_forward_median(tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                                   gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                                   background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                                   out_depth: _float_array, out_last: _int_array, contributed: _int_array,
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
                           out_depth: _float_array, out_last: _int_array, contributed: _int_array):
    """One thread per tile of the band that starts at `first_tile`."""
    _composite_tile_forward(first_tile + wp.tid(), tiles_x, width, height, tile_ranges, gaussian_ids, pair_masks,
                            records, background, out_rgb, out_transmittance, out_depth, out_last, contributed)


@wp.kernel
def composite_forward_median_simd(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: _int_array,
                                  gaussian_ids: _int_array, pair_masks: _int_array, records: _float_array,
                                  background: _float_array, out_rgb: _float_array, out_transmittance: _float_array,
                                  out_depth: _float_array, out_last: _int_array, contributed: _int_array,
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
