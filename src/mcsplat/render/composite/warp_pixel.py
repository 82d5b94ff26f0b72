"""What the two families of Warp compositing kernels share, per pixel: the scalar kernels of warp_scalar.py (a thread
per pixel) and the tile kernels of warp_tiles.py (a block of threads per tile) call these functions, so both do the
same arithmetic in the same order (test_composite_tiles.py holds the tile forward to the scalar one's image, to the
bit). The formulas are in warp_scalar.py's docstring.

- pixel_in_tile: a pixel of a tile and the bit of its 4x4 block;
- forward: a Gaussian's alpha at a pixel centre, and the pixel's outputs;
- backward: the pixel's upstream gradients, and one step of the back-to-front walk over the Gaussians the pixel
  used, with the pixel's ten gradient terms for that Gaussian (a record, in the order of RECORD_WIDTH's comment).

(No `from __future__ import annotations` here, nor in the kernel modules: Warp reads the annotations as live objects,
and most types are made per scalar type, as local names of the functions below.)
"""

import functools
from typing import Any, NamedTuple

import warp as wp

from ..constants import ALPHA_MAX, ALPHA_MIN, BLOCK_SIZE, POWER_SKIP, TILE_SIZE

# A Gaussian's ten numbers, in the order of the tile kernels' shared memory and gradient buffer: mean x, y; conic a,
# b, c; opacity; colour r, g, b; depth.
RECORD_WIDTH = 10

IntArray1 = wp.array(dtype=wp.int32)
IntArray2 = wp.array2d(dtype=wp.int32)


@functools.lru_cache(maxsize=None)
def vector_type(length: int, dtype):
    return wp.types.vector(length, dtype)


def record_type(dtype):
    """A Gaussian's ten numbers (see RECORD_WIDTH) as one vector of scalar type dtype."""
    return vector_type(RECORD_WIDTH, dtype)


@functools.lru_cache(maxsize=None)
def array_types(dtype) -> tuple:
    """(Array1, Array2, Array3): the kernels' 1-, 2- and 3-dimensional arrays of scalar type dtype."""
    return wp.array(dtype=dtype), wp.array2d(dtype=dtype), wp.array3d(dtype=dtype)


@wp.func
def pixel_in_tile(tile: int, local: int, tiles_x: int):
    """(pixel x, pixel y, bit of the pixel's 4x4 block) of pixel `local` (row-major) of `tile`."""
    px = (tile % tiles_x) * TILE_SIZE + local % TILE_SIZE
    py = (tile / tiles_x) * TILE_SIZE + local / TILE_SIZE
    block_bit = 1 << ((local / TILE_SIZE / BLOCK_SIZE) * BLOCK_SIZE + (local % TILE_SIZE) / BLOCK_SIZE)
    return px, py, block_bit


class PixelFunctions(NamedTuple):
    """The Warp functions of one scalar type (pixel_functions), and the two structs the backward carries."""
    centre: Any          # (px, py) -> the pixel centre (x, y)
    alpha: Any           # a Gaussian's alpha at the pixel centre, 0 where the power test skips it
    write: Any           # the forward's outputs of one pixel
    upstream: Any        # (last contributor, Upstream) of a pixel
    start_walk: Any      # the backward walk's state before its first (backmost) Gaussian
    falloff: Any         # (dx, dy, power, gauss, raw alpha, alpha) of a Gaussian at the pixel centre
    passes: Any          # the forward's tests on power and alpha: whether the pixel composited the Gaussian
    step_back: Any       # (Walk, ten gradient terms) of a Gaussian the pixel composited
    Upstream: Any
    Walk: Any


@functools.lru_cache(maxsize=None)
def pixel_functions(dtype) -> PixelFunctions:
    """The shared Warp functions for scalar type wp.float32 or wp.float64."""
    vec3 = vector_type(3, dtype)
    record = record_type(dtype)
    Array1, Array2, Array3 = array_types(dtype)
    zero = dtype(0.0)
    one = dtype(1.0)

    @wp.struct
    class Upstream:
        """A pixel's upstream gradients and what the backward reads with them."""
        t_final: dtype       # the forward's final transmittance
        dl_drgb: vec3
        dl_ddepth: dtype
        dl_dalpha_out: dtype
        bg_term: dtype       # background . dl_drgb

    @wp.struct
    class Walk:
        """The backward walk's state in front of the Gaussian last stepped over."""
        transmittance: dtype
        behind_rgb: vec3     # colour composited behind the current Gaussian
        behind_depth: dtype
        next_alpha: dtype    # the Gaussian last stepped over (the one behind the next)
        next_rgb: vec3
        next_depth: dtype

    @wp.func
    def centre(px: int, py: int):
        return dtype(px) + dtype(0.5), dtype(py) + dtype(0.5)

    @wp.func
    def power_at(dx: dtype, dy: dtype, ca: dtype, cb: dtype, cc: dtype):
        return dtype(-0.5) * (ca * dx * dx + cc * dy * dy) - cb * dx * dy

    @wp.func
    def alpha(mx: dtype, my: dtype, ca: dtype, cb: dtype, cc: dtype, opacity: dtype, pix_x: dtype, pix_y: dtype):
        power = power_at(mx - pix_x, my - pix_y, ca, cb, cc)
        if power > zero or power < dtype(POWER_SKIP):
            return zero  # below ALPHA_MIN: skipped like a faint Gaussian
        return wp.min(dtype(ALPHA_MAX), opacity * wp.exp(power))

    @wp.func
    def write(px: int, py: int, rgb: vec3, transmittance: dtype, depth: dtype, last: int, background: Array1,
              out_rgb: Array3, out_transmittance: Array2, out_depth: Array2, out_last: IntArray2):
        for ch in range(3):
            out_rgb[py, px, ch] = rgb[ch] + transmittance * background[ch]
        out_transmittance[py, px] = transmittance
        out_depth[py, px] = depth
        out_last[py, px] = last

    @wp.func
    def upstream(px: int, py: int, width: int, height: int, final_transmittance: Array2,
                 last_contributor: IntArray2, grad_rgb: Array3, grad_alpha: Array2, grad_depth: Array2,
                 background: Array1):
        """A pixel outside the image (a partial tile) reads its nearest pixel's numbers, with last contributor 0."""
        qx = wp.min(px, width - 1)
        qy = wp.min(py, height - 1)
        last = int(0)
        if px < width and py < height:
            last = last_contributor[qy, qx]
        pixel = Upstream()
        pixel.t_final = final_transmittance[qy, qx]
        pixel.dl_drgb = vec3(grad_rgb[qy, qx, 0], grad_rgb[qy, qx, 1], grad_rgb[qy, qx, 2])
        pixel.dl_ddepth = grad_depth[qy, qx]
        pixel.dl_dalpha_out = grad_alpha[qy, qx]
        pixel.bg_term = wp.dot(vec3(background[0], background[1], background[2]), pixel.dl_drgb)
        return last, pixel

    @wp.func
    def start_walk(pixel: Upstream):
        walk = Walk()
        walk.transmittance = pixel.t_final
        walk.behind_rgb = vec3(zero, zero, zero)
        walk.behind_depth = zero
        walk.next_alpha = zero
        walk.next_rgb = vec3(zero, zero, zero)
        walk.next_depth = zero
        return walk

    @wp.func
    def falloff(mx: dtype, my: dtype, ca: dtype, cb: dtype, cc: dtype, opacity: dtype, pix_x: dtype, pix_y: dtype):
        dx = mx - pix_x
        dy = my - pix_y
        power = power_at(dx, dy, ca, cb, cc)
        gauss = wp.exp(wp.min(power, zero))
        raw_alpha = opacity * gauss
        return dx, dy, power, gauss, raw_alpha, wp.min(dtype(ALPHA_MAX), raw_alpha)

    @wp.func
    def passes(power: dtype, alpha: dtype):
        return power <= zero and power >= dtype(POWER_SKIP) and alpha >= dtype(ALPHA_MIN)

    @wp.func
    def step_back(walk: Walk, pixel: Upstream, alpha: dtype, raw_alpha: dtype, gauss: dtype, color: vec3,
                  depth: dtype, dx: dtype, dy: dtype, ca: dtype, cb: dtype, cc: dtype):
        """T_i recovered by division, then dL/dalpha_i from what lies behind and the background."""
        one_minus_alpha = one - alpha
        after = Walk()
        after.transmittance = walk.transmittance / one_minus_alpha
        after.behind_rgb = walk.next_alpha * walk.next_rgb + (one - walk.next_alpha) * walk.behind_rgb
        after.behind_depth = walk.next_alpha * walk.next_depth + (one - walk.next_alpha) * walk.behind_depth
        after.next_alpha = alpha
        after.next_rgb = color
        after.next_depth = depth
        weight = alpha * after.transmittance
        dl_dalpha = after.transmittance * (wp.dot(color - after.behind_rgb, pixel.dl_drgb)
                                           + (depth - after.behind_depth) * pixel.dl_ddepth)
        # The background and the output alpha (1 - T_final) both depend on alpha through T_final.
        dl_dalpha = dl_dalpha + (pixel.t_final / one_minus_alpha) * (pixel.dl_dalpha_out - pixel.bg_term)
        d_opacity = zero
        dl_dpower = zero
        if raw_alpha <= dtype(ALPHA_MAX):  # clamped: alpha no longer depends on opacity or position
            d_opacity = gauss * dl_dalpha
            dl_dpower = raw_alpha * dl_dalpha
        terms = record(-dl_dpower * (ca * dx + cb * dy), -dl_dpower * (cb * dx + cc * dy),
                       dtype(-0.5) * dl_dpower * dx * dx, -dl_dpower * dx * dy, dtype(-0.5) * dl_dpower * dy * dy,
                       d_opacity, weight * pixel.dl_drgb[0], weight * pixel.dl_drgb[1], weight * pixel.dl_drgb[2],
                       weight * pixel.dl_ddepth)
        return after, terms

    return PixelFunctions(centre, alpha, write, upstream, start_walk, falloff, passes, step_back, Upstream, Walk)
