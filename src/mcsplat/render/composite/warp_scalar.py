"""Warp kernels for alpha compositing (forward) and its hand-written backward.

One thread per pixel, pixels in tile-major order: thread t of a launch works on pixel (t % 256) of tile
`first_tile + t // 256`, like one CUDA block per tile. A launch can cover a band of tiles, so the CPU launcher can
run bands in parallel. Per pixel, front to back (3DGS):

    alpha_i = min(0.99, o_i * exp(-0.5 d^T Q d)),  d = mean_i - pixel centre,  Q the conic
    skip alpha_i < 1/255; stop before the transmittance would fall below 1e-4
    C = sum_i alpha_i T_i c_i + T_final * background,   D = sum_i alpha_i T_i z_i
    median Gaussian (a second forward kernel, for callers that ask) = the last i composited with T_i > 0.5, where
    the accumulated alpha first reaches 0.5 (render/outputs/median.py turns it into the median depth)

Each pair carries a mask of the 4x4-pixel blocks of its tile the Gaussian can reach (bin/); a pixel skips a
pair whose block bit is clear, which only spares work. The backward walks the same list back to front from the last
contributor, recovering T_i by division, and adds gradients for the 2D means, conics, opacities, colours and depths.
Warp's automatic differentiation is not used: it returns wrong gradients for this loop (dynamic range with an early
exit) without any error.

On CUDA the 32 threads of a warp (32 pixels of one tile) walk the list in step, from the warp's last contributor, and
sum their 10 gradient terms for the Gaussian with shuffles before one lane adds them to memory: one atomic add per
warp instead of one per pixel (gsplat does the same). On the CPU, and for float64, the lane helpers below do nothing
and every pixel adds its own terms.
"""

from __future__ import annotations

import functools

import warp as wp

from ..constants import (ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, MEDIAN_TRANSMITTANCE, PIXELS_PER_TILE, POWER_SKIP,
                        TILE_SIZE, TRANSMITTANCE_MIN)


@wp.func
def pixel_of_thread(t: int, first_tile: int, tiles_x: int):
    """(tile, pixel x, pixel y, bit of the pixel's 4x4 block) of thread t: 256 consecutive threads per tile."""
    tile = first_tile + t / PIXELS_PER_TILE
    local = t % PIXELS_PER_TILE
    px = (tile % tiles_x) * TILE_SIZE + local % TILE_SIZE
    py = (tile / tiles_x) * TILE_SIZE + local / TILE_SIZE
    block_bit = 1 << ((local / TILE_SIZE / BLOCK_SIZE) * BLOCK_SIZE + (local % TILE_SIZE) / BLOCK_SIZE)
    return tile, px, py, block_bit


# Warp-level helpers of the float32 backward (`_lanes`): shuffles across the 32 lanes on CUDA, a single lane in CPU
# code. The float64 kernels use the single-lane versions (`_one`) everywhere: Warp's CUDA headers have no float64
# shuffles. With one lane, the sum and maximum are the value itself and every thread leads.
_ON_CUDA = "#if defined(__CUDA_ARCH__)\n{cuda}\n#else\n{cpu}\n#endif\n"
_FULL_WARP = "0xffffffffu"


@wp.func_native(_ON_CUDA.format(
    cuda=f"float v = value;\nfor (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync({_FULL_WARP}, v, o);\nreturn v;",
    cpu="return value;"))
def _warp_sum_lanes(value: wp.float32) -> wp.float32: ...


@wp.func_native(_ON_CUDA.format(
    cuda=f"int v = value;\nfor (int o = 16; o > 0; o >>= 1) {{ int w = __shfl_xor_sync({_FULL_WARP}, v, o); "
         f"v = w > v ? w : v; }}\nreturn v;",
    cpu="return value;"))
def _warp_max_lanes(value: int) -> int: ...


@wp.func_native(_ON_CUDA.format(cuda=f"return __ballot_sync({_FULL_WARP}, flag) != 0 ? 1 : 0;", cpu="return flag;"))
def _warp_any_lanes(flag: int) -> int: ...


@wp.func_native(_ON_CUDA.format(cuda="return (threadIdx.x & 31) == 0 ? 1 : 0;", cpu="return 1;"))
def _leads_warp_lanes() -> int: ...


@wp.func
def _warp_sum_one(value: wp.float64):
    return value


@wp.func
def _warp_max_one(value: int):
    return value


@wp.func
def _warp_any_one(flag: int):
    return flag


@wp.func
def _leads_warp_one():
    return 1


@functools.lru_cache(maxsize=None)
def composite_kernels(dtype):
    """(forward, backward) kernels for scalar type wp.float32 or wp.float64."""
    return _forward_kernel(dtype, with_median=False), _backward_kernel(dtype)


def median_forward_kernel(dtype):
    """The forward kernel that also writes each pixel's median Gaussian (out_median, -1 where none; the plain one
    leaves it alone)."""
    return _forward_kernel(dtype, with_median=True)


@functools.lru_cache(maxsize=None)
def _forward_kernel(dtype, with_median: bool):
    # Two kernels from one body: wp.static drops the median's lines from the training kernel at compile time.
    vec3 = wp.types.vector(3, dtype)

    @wp.kernel(module="unique")
    def composite_forward(
        first_tile: int, tiles_x: int, width: int, height: int,
        tile_ranges: wp.array2d(dtype=wp.int32), gaussian_ids: wp.array(dtype=wp.int32),
        pair_masks: wp.array(dtype=wp.int32),
        means2d: wp.array2d(dtype=dtype), conics: wp.array2d(dtype=dtype), opacities: wp.array(dtype=dtype),
        colors: wp.array2d(dtype=dtype), depths: wp.array(dtype=dtype), background: wp.array(dtype=dtype),
        out_rgb: wp.array3d(dtype=dtype), out_transmittance: wp.array2d(dtype=dtype),
        out_depth: wp.array2d(dtype=dtype), out_last: wp.array2d(dtype=wp.int32),
        contributed: wp.array(dtype=wp.int32), out_median: wp.array2d(dtype=wp.int32),
    ):
        tile, px, py, block_bit = pixel_of_thread(wp.tid(), first_tile, tiles_x)
        if px >= width or py >= height:
            return
        pix_x = dtype(px) + dtype(0.5)
        pix_y = dtype(py) + dtype(0.5)
        start = tile_ranges[tile, 0]
        end = tile_ranges[tile, 1]

        transmittance = dtype(1.0)
        rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        depth = dtype(0.0)
        median = int(-1)
        last = int(0)
        for k in range(start, end):
            if (pair_masks[k] & block_bit) == 0:
                continue
            g = gaussian_ids[k]
            dx = means2d[g, 0] - pix_x
            dy = means2d[g, 1] - pix_y
            power = dtype(-0.5) * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) - conics[g, 1] * dx * dy
            if power > dtype(0.0) or power < dtype(POWER_SKIP):
                continue
            alpha = wp.min(dtype(ALPHA_MAX), opacities[g] * wp.exp(power))
            if alpha < dtype(ALPHA_MIN):
                continue
            next_transmittance = transmittance * (dtype(1.0) - alpha)
            if next_transmittance < dtype(TRANSMITTANCE_MIN):
                break
            weight = alpha * transmittance
            rgb = rgb + weight * vec3(colors[g, 0], colors[g, 1], colors[g, 2])
            depth = depth + weight * depths[g]
            if wp.static(with_median):
                if transmittance > dtype(MEDIAN_TRANSMITTANCE):
                    median = g
            transmittance = next_transmittance
            last = k - start + 1
            contributed[g] = 1

        for ch in range(3):
            out_rgb[py, px, ch] = rgb[ch] + transmittance * background[ch]
        out_transmittance[py, px] = transmittance
        out_depth[py, px] = depth
        out_last[py, px] = last
        if wp.static(with_median):
            out_median[py, px] = median

    return composite_forward


@functools.lru_cache(maxsize=None)
def _backward_kernel(dtype):
    vec3 = wp.types.vector(3, dtype)
    single = dtype == wp.float32
    warp_sum = _warp_sum_lanes if single else _warp_sum_one
    warp_max = _warp_max_lanes if single else _warp_max_one
    warp_any = _warp_any_lanes if single else _warp_any_one
    leads_warp = _leads_warp_lanes if single else _leads_warp_one

    @wp.kernel(module="unique")
    def composite_backward(
        first_tile: int, tiles_x: int, width: int, height: int,
        tile_ranges: wp.array2d(dtype=wp.int32), gaussian_ids: wp.array(dtype=wp.int32),
        pair_masks: wp.array(dtype=wp.int32),
        means2d: wp.array2d(dtype=dtype), conics: wp.array2d(dtype=dtype), opacities: wp.array(dtype=dtype),
        colors: wp.array2d(dtype=dtype), depths: wp.array(dtype=dtype), background: wp.array(dtype=dtype),
        final_transmittance: wp.array2d(dtype=dtype), last_contributor: wp.array2d(dtype=wp.int32),
        grad_rgb: wp.array3d(dtype=dtype), grad_alpha: wp.array2d(dtype=dtype), grad_depth: wp.array2d(dtype=dtype),
        grad_means2d: wp.array2d(dtype=dtype), grad_conics: wp.array2d(dtype=dtype),
        grad_opacities: wp.array(dtype=dtype), grad_colors: wp.array2d(dtype=dtype),
        grad_depths: wp.array(dtype=dtype),
    ):
        tile, px, py, block_bit = pixel_of_thread(wp.tid(), first_tile, tiles_x)
        # A pixel outside the image (a partial tile) stays in the loop, contributing nothing: its warp's shuffles
        # need every lane.
        inside = px < width and py < height
        qx = wp.min(px, width - 1)
        qy = wp.min(py, height - 1)
        pix_x = dtype(px) + dtype(0.5)
        pix_y = dtype(py) + dtype(0.5)
        start = tile_ranges[tile, 0]
        last = int(0)
        if inside:
            last = last_contributor[qy, qx]

        t_final = final_transmittance[qy, qx]
        dl_drgb = vec3(grad_rgb[qy, qx, 0], grad_rgb[qy, qx, 1], grad_rgb[qy, qx, 2])
        dl_ddepth = grad_depth[qy, qx]
        dl_dalpha_out = grad_alpha[qy, qx]
        bg = vec3(background[0], background[1], background[2])
        bg_term = wp.dot(bg, dl_drgb)

        transmittance = t_final
        behind_rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))  # colour composited behind the current Gaussian
        behind_depth = dtype(0.0)
        next_alpha = dtype(0.0)
        next_rgb = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        next_depth = dtype(0.0)
        zero = dtype(0.0)
        for j in range(warp_max(last) - 1, -1, -1):
            g = gaussian_ids[start + j]
            dx = means2d[g, 0] - pix_x
            dy = means2d[g, 1] - pix_y
            ca = conics[g, 0]
            cb = conics[g, 1]
            cc = conics[g, 2]
            power = dtype(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
            gauss = wp.exp(wp.min(power, zero))
            raw_alpha = opacities[g] * gauss
            alpha = wp.min(dtype(ALPHA_MAX), raw_alpha)
            used = (j < last and (pair_masks[start + j] & block_bit) != 0 and power <= zero
                    and power >= dtype(POWER_SKIP) and alpha >= dtype(ALPHA_MIN))
            # The ten terms of this pixel (zero where it does not use the Gaussian).
            d_color = vec3(zero, zero, zero)
            d_depth = zero
            d_opacity = zero
            d_mean_x = zero
            d_mean_y = zero
            d_conic_a = zero
            d_conic_b = zero
            d_conic_c = zero
            if used:
                one_minus_alpha = dtype(1.0) - alpha
                transmittance = transmittance / one_minus_alpha
                weight = alpha * transmittance
                color = vec3(colors[g, 0], colors[g, 1], colors[g, 2])
                depth = depths[g]
                d_color = weight * dl_drgb
                d_depth = weight * dl_ddepth

                behind_rgb = next_alpha * next_rgb + (dtype(1.0) - next_alpha) * behind_rgb
                behind_depth = next_alpha * next_depth + (dtype(1.0) - next_alpha) * behind_depth
                next_alpha = alpha
                next_rgb = color
                next_depth = depth

                dl_dalpha = transmittance * (wp.dot(color - behind_rgb, dl_drgb) + (depth - behind_depth) * dl_ddepth)
                # The background and the output alpha (1 - T_final) both depend on alpha through T_final.
                dl_dalpha = dl_dalpha + (t_final / one_minus_alpha) * (dl_dalpha_out - bg_term)
                if raw_alpha <= dtype(ALPHA_MAX):  # clamped: alpha no longer depends on opacity or position
                    d_opacity = gauss * dl_dalpha
                    dl_dpower = raw_alpha * dl_dalpha
                    d_mean_x = -dl_dpower * (ca * dx + cb * dy)
                    d_mean_y = -dl_dpower * (cb * dx + cc * dy)
                    d_conic_a = dtype(-0.5) * dl_dpower * dx * dx
                    d_conic_b = -dl_dpower * dx * dy
                    d_conic_c = dtype(-0.5) * dl_dpower * dy * dy
            if warp_any(wp.where(used, 1, 0)) == 0:
                continue
            d_color = vec3(warp_sum(d_color[0]), warp_sum(d_color[1]), warp_sum(d_color[2]))
            d_depth = warp_sum(d_depth)
            d_opacity = warp_sum(d_opacity)
            d_mean_x = warp_sum(d_mean_x)
            d_mean_y = warp_sum(d_mean_y)
            d_conic_a = warp_sum(d_conic_a)
            d_conic_b = warp_sum(d_conic_b)
            d_conic_c = warp_sum(d_conic_c)
            if leads_warp() == 1:  # lane 0 on CUDA; every pixel that used it elsewhere
                for ch in range(3):
                    wp.atomic_add(grad_colors, g, ch, d_color[ch])
                wp.atomic_add(grad_depths, g, d_depth)
                wp.atomic_add(grad_opacities, g, d_opacity)
                wp.atomic_add(grad_means2d, g, 0, d_mean_x)
                wp.atomic_add(grad_means2d, g, 1, d_mean_y)
                wp.atomic_add(grad_conics, g, 0, d_conic_a)
                wp.atomic_add(grad_conics, g, 1, d_conic_b)
                wp.atomic_add(grad_conics, g, 2, d_conic_c)

    return composite_backward
