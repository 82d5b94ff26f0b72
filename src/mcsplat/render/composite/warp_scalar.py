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

import functools

import warp as wp

from ..constants import ALPHA_MIN, MEDIAN_TRANSMITTANCE, PIXELS_PER_TILE, TRANSMITTANCE_MIN
from .warp_pixel import (RECORD_WIDTH, IntArray1, IntArray2, array_types, pixel_functions, pixel_in_tile,
                         record_type, vector_type)


@wp.func
def pixel_of_thread(t: int, first_tile: int, tiles_x: int):
    """(tile, pixel x, pixel y, bit of the pixel's 4x4 block) of thread t: 256 consecutive threads per tile."""
    tile = first_tile + t / PIXELS_PER_TILE
    px, py, block_bit = pixel_in_tile(tile, t % PIXELS_PER_TILE, tiles_x)
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
    vec3 = vector_type(3, dtype)
    pixel = pixel_functions(dtype)
    Array1, Array2, Array3 = array_types(dtype)

    @wp.kernel(module="unique")
    def composite_forward(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: IntArray2,
                          gaussian_ids: IntArray1, pair_masks: IntArray1, means2d: Array2, conics: Array2,
                          opacities: Array1, colors: Array2, depths: Array1, background: Array1, out_rgb: Array3,
                          out_transmittance: Array2, out_depth: Array2, out_last: IntArray2, contributed: IntArray1,
                          out_median: IntArray2):
        tile, px, py, block_bit = pixel_of_thread(wp.tid(), first_tile, tiles_x)
        if px >= width or py >= height:
            return
        pix_x, pix_y = pixel.centre(px, py)
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
            alpha = pixel.alpha(means2d[g, 0], means2d[g, 1], conics[g, 0], conics[g, 1], conics[g, 2], opacities[g],
                                pix_x, pix_y)
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

        pixel.write(px, py, rgb, transmittance, depth, last, background, out_rgb, out_transmittance, out_depth,
                    out_last)
        if wp.static(with_median):
            out_median[py, px] = median

    return composite_forward


@functools.lru_cache(maxsize=None)
def _backward_kernel(dtype):
    vec3 = vector_type(3, dtype)
    record = record_type(dtype)
    pixel = pixel_functions(dtype)
    Array1, Array2, Array3 = array_types(dtype)
    single = dtype == wp.float32
    warp_sum = _warp_sum_lanes if single else _warp_sum_one
    warp_max = _warp_max_lanes if single else _warp_max_one
    warp_any = _warp_any_lanes if single else _warp_any_one
    leads_warp = _leads_warp_lanes if single else _leads_warp_one

    @wp.kernel(module="unique")
    def composite_backward(first_tile: int, tiles_x: int, width: int, height: int, tile_ranges: IntArray2,
                           gaussian_ids: IntArray1, pair_masks: IntArray1, means2d: Array2, conics: Array2,
                           opacities: Array1, colors: Array2, depths: Array1, background: Array1,
                           final_transmittance: Array2, last_contributor: IntArray2, grad_rgb: Array3,
                           grad_alpha: Array2, grad_depth: Array2, grad_means2d: Array2, grad_conics: Array2,
                           grad_opacities: Array1, grad_colors: Array2, grad_depths: Array1):
        tile, px, py, block_bit = pixel_of_thread(wp.tid(), first_tile, tiles_x)
        # A pixel outside the image (a partial tile) stays in the loop with last contributor 0, contributing nothing:
        # its warp's shuffles need every lane.
        pix_x, pix_y = pixel.centre(px, py)
        start = tile_ranges[tile, 0]
        last, upstream = pixel.upstream(px, py, width, height, final_transmittance, last_contributor, grad_rgb,
                                        grad_alpha, grad_depth, background)
        walk = pixel.start_walk(upstream)
        for j in range(warp_max(last) - 1, -1, -1):
            g = gaussian_ids[start + j]
            ca = conics[g, 0]
            cb = conics[g, 1]
            cc = conics[g, 2]
            dx, dy, power, gauss, raw_alpha, alpha = pixel.falloff(means2d[g, 0], means2d[g, 1], ca, cb, cc,
                                                                   opacities[g], pix_x, pix_y)
            used = j < last and (pair_masks[start + j] & block_bit) != 0 and pixel.passes(power, alpha)
            terms = record()  # this pixel's ten terms, zero where it does not use the Gaussian
            if used:
                color = vec3(colors[g, 0], colors[g, 1], colors[g, 2])
                walk, terms = pixel.step_back(walk, upstream, alpha, raw_alpha, gauss, color, depths[g], dx, dy, ca,
                                              cb, cc)
            if warp_any(wp.where(used, 1, 0)) == 0:
                continue
            for term in range(RECORD_WIDTH):
                terms[term] = warp_sum(terms[term])
            if leads_warp() == 1:  # lane 0 on CUDA; every pixel that used it elsewhere
                wp.atomic_add(grad_means2d, g, 0, terms[0])
                wp.atomic_add(grad_means2d, g, 1, terms[1])
                for k in range(3):
                    wp.atomic_add(grad_conics, g, k, terms[2 + k])
                wp.atomic_add(grad_opacities, g, terms[5])
                for ch in range(3):
                    wp.atomic_add(grad_colors, g, ch, terms[6 + ch])
                wp.atomic_add(grad_depths, g, terms[9])

    return composite_backward
