"""Fused SSIM for float32 images on the CPU: the mean SSIM of losses.py (and the L1 term beside it) with their
gradient, in one kernel forward and one backward.

torch's depthwise convolution is slow on the CPU (the loss took 40-60 ms of a 400x400 training step); here the
separable 11-tap Gaussian window runs as plain C++ loops over contiguous rows that clang vectorises. With the
windowed statistics mu_x, mu_y, <x^2>, <y^2>, <xy> of each pixel and channel,

    S = (2 mu_x mu_y + C1)(2 cov + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2)),

and since the zero-padded symmetric window is its own adjoint,

    d mean(S) / dx = [blur(dS/dmu_x) + 2 x blur(dS/d<x^2>) + y blur(dS/d<xy>)] / (3 H W).

Forward: each CPU thread takes a range of rows; for each channel it blurs the five statistics of a row along the row
into a ring of the last 11 rows, blurs them down the columns from the ring, and keeps S's three partial derivatives
(and each row's sums of S and of |x - y|). Backward: the same for the three partials, combined into the gradient
with L1's sign(x - y). The rows a range's window reaches beyond it are blurred by that range too, so every output
row is computed the same way whatever the threads (the result does not depend on them). Holding the row-blurred
rows in the ring instead of 15 full planes halved the forward's time at 800x600; summing each blurred value's 11 taps
in a register, and the rows' sums in lanes outside the pixel loops (a running double sum kept clang from vectorising
the loop it sat in), halved it again. CUDA and float64 keep the other paths of losses.py.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from .compute.cpu_target import kernel_flags
from .compute.runtime import cpu_threads, ensure_warp, flat_view, run_ranges
from .ssim_warp import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW

# The window and constants are defined once, in ssim_warp.py.
_WINDOW, _SIGMA, _C1, _C2 = SSIM_WINDOW, SSIM_SIGMA, SSIM_C1, SSIM_C2


def _window() -> list[float]:
    weights = [math.exp(-(k - _WINDOW // 2) ** 2 / (2 * _SIGMA ** 2)) for k in range(_WINDOW)]
    total = sum(weights)
    return [w / total for w in weights]


_TAPS = ", ".join(f"{float(torch.tensor(w, dtype=torch.float32))!r}f" for w in _window())

# Each launch item is a range of output rows (one per CPU thread). A row's five statistics (or three partials) are
# blurred along the row once, into a ring of the last WINDOW rows, and blurred down the columns from there: the
# row-blurred planes never leave the thread's cache (the passes before wrote and read back 15 full planes).
_HELPERS = f"""
    const float taps[{_WINDOW}] = {{{_TAPS}}};
    const int half = {_WINDOW // 2}, window = {_WINDOW};
    const int w = width, h = height;
    const long plane = (long)w * h;
    const int first = (int)((long)part * h / parts), last = (int)((long)(part + 1) * h / parts);
    // Each output is summed in a register over the 11 taps (a fixed count, so the loop over k unrolls and the loop
    // over j vectorises), rather than added into `out` tap by tap: one store a value instead of eleven.
    auto blur_row = [&](const float* __restrict padded, float* __restrict out) {{  // padded[0 .. w + 2 half) -> w
        for (int j = 0; j < w; ++j) {{
            float sum = taps[0] * padded[j];
            for (int k = 1; k < {_WINDOW}; ++k) sum += taps[k] * padded[j + k];
            out[j] = sum;
        }}
    }};
    // A sum in double over 8 lanes: a single running sum would keep the loop it sits in from being vectorised.
    auto sum_lanes = [](const float* values, int count) {{
        double lanes[8] = {{0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0}};
        int j = 0;
        for (; j + 8 <= count; j += 8)
            for (int k = 0; k < 8; ++k) lanes[k] += values[j + k];
        double total = 0.0;
        for (; j < count; ++j) total += values[j];
        for (int k = 0; k < 8; ++k) total += lanes[k];
        return total;
    }};
    // The rows of the window around `row` inside the image, blurred down the columns from the ring (maps of w);
    // rows outside the image are read from `zeros` (maps of w zeros), which adds nothing.
    auto blur_column = [&](const float* ring, const float* zeros, int maps, int row, float* __restrict out) {{
        const float* rows[{_WINDOW}];
        for (int k = 0; k < window; ++k) {{
            const int source = row + k - half;
            rows[k] = source < 0 || source >= h ? zeros : ring + (long)(source % window) * maps * w;
        }}
        for (int j = 0; j < maps * w; ++j) {{
            float sum = 0.0f;
            for (int k = 0; k < {_WINDOW}; ++k) sum += taps[k] * rows[k][j];
            out[j] = sum;
        }}
    }};
"""

_FORWARD = _HELPERS + f"""
    const float* x = (const float*)image.data;
    const float* y = (const float*)target.data;
    float* partial = (float*)partials.data;
    double* sums = (double*)row_sums.data;
    double* l1 = (double*)l1_sums.data;
    const int stride = w + 2 * half;
    // This part's room in `scratch` (forward_scratch_floats): a 4K image's ring (845 KB) is more than some
    // platforms give a thread's stack, and torch's allocation fails with a clear error where malloc's would crash.
    float* ring = (float*)scratch.data + (long)part * scratch_floats;
    float* padded = ring + window * 5 * w;
    float* stat = padded + 5 * stride;
    float* zeros = stat + 6 * w;
    for (int j = 0; j < 5 * w; ++j) zeros[j] = 0.0f;
    for (int s = 0; s < 5; ++s)
        for (int j = 0; j < half; ++j) padded[s * stride + j] = padded[s * stride + half + w + j] = 0.0f;
    for (int row = first; row < last; ++row) {{
        sums[row] = 0.0;
        const float* xr = x + (long)row * w * 3;
        const float* yr = y + (long)row * w * 3;
        for (int j = 0; j < 3 * w; ++j) stat[j] = fabsf(xr[j] - yr[j]);
        l1[row] = sum_lanes(stat, 3 * w);  // the L1 loss's share of the row, read while the pixels are at hand
    }}
    for (int c = 0; c < 3; ++c) {{
        int next = first - half < 0 ? 0 : first - half;  // the next row to blur along
        for (int row = first; row < last; ++row) {{
            const int need = row + half < h ? row + half : h - 1;
            for (; next <= need; ++next) {{
                const float* xr = x + (long)next * w * 3;
                const float* yr = y + (long)next * w * 3;
                float* p = padded + half;
                for (int j = 0; j < w; ++j) {{
                    const float xv = xr[3 * j + c], yv = yr[3 * j + c];
                    p[j] = xv; p[stride + j] = yv; p[2 * stride + j] = xv * xv;
                    p[3 * stride + j] = yv * yv; p[4 * stride + j] = xv * yv;
                }}
                float* slot = ring + (long)(next % window) * 5 * w;
                for (int s = 0; s < 5; ++s) blur_row(padded + s * stride, slot + s * w);
            }}
            blur_column(ring, zeros, 5, row, stat);
            float* d_mu = partial + (0 * 3 + c) * plane + (long)row * w;
            float* d_xx = partial + (1 * 3 + c) * plane + (long)row * w;
            float* d_xy = partial + (2 * 3 + c) * plane + (long)row * w;
            float* similarity = stat + 5 * w;
            for (int j = 0; j < w; ++j) {{
                const float mx = stat[j], my = stat[w + j];
                const float var_x = stat[2 * w + j] - mx * mx, var_y = stat[3 * w + j] - my * my;
                const float cov = stat[4 * w + j] - mx * my;
                const float a = 2.0f * mx * my + {_C1!r}f, b = 2.0f * cov + {_C2!r}f;
                const float cc = mx * mx + my * my + {_C1!r}f, d = var_x + var_y + {_C2!r}f;
                const float inv = 1.0f / (cc * d);
                const float s = a * b * inv;
                similarity[j] = s;
                d_mu[j] = 2.0f * my * (b - a) * inv - 2.0f * s * mx / cc + 2.0f * s * mx / d;
                d_xx[j] = -s / d;
                d_xy[j] = 2.0f * a * inv;
            }}
            sums[row] += sum_lanes(similarity, w);
        }}
    }}
"""

_BACKWARD = _HELPERS + """
    const float* in = (const float*)partials.data;
    const float* x = (const float*)image.data;
    const float* y = (const float*)target.data;
    float* grad = (float*)grad_image.data;
    const int stride = w + 2 * half;
    float* ring = (float*)scratch.data + (long)part * scratch_floats;  // backward_scratch_floats
    float* padded = ring + window * 3 * w;
    float* b = padded + stride;
    float* zeros = b + 3 * w;
    for (int j = 0; j < 3 * w; ++j) zeros[j] = 0.0f;
    for (int j = 0; j < half; ++j) padded[j] = padded[half + w + j] = 0.0f;
    for (int c = 0; c < 3; ++c) {
        int next = first - half < 0 ? 0 : first - half;
        for (int row = first; row < last; ++row) {
            const int need = row + half < h ? row + half : h - 1;
            for (; next <= need; ++next) {
                float* slot = ring + (long)(next % window) * 3 * w;
                for (int q = 0; q < 3; ++q) {
                    const float* source = in + (q * 3 + c) * plane + (long)next * w;
                    for (int j = 0; j < w; ++j) padded[half + j] = source[j];
                    blur_row(padded, slot + q * w);
                }
            }
            blur_column(ring, zeros, 3, row, b);
            const float* xr = x + (long)row * w * 3;
            const float* yr = y + (long)row * w * 3;
            float* g = grad + (long)row * w * 3;
            for (int j = 0; j < w; ++j) {
                const float xv = xr[3 * j + c], yv = yr[3 * j + c];
                const float sign = xv > yv ? 1.0f : xv < yv ? -1.0f : 0.0f;  // |x - y|'s, 0 where they are equal
                g[3 * j + c] = scale * (b[j] + 2.0f * xv * b[w + j] + yv * b[2 * w + j]) + l1_scale * sign;
            }
        }
    }
"""

# Fused multiply-add in the blur loops (Warp's default keeps a * b + c as two roundings).
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-ffp-contract=fast")})

_floats = wp.array(dtype=wp.float32)


@wp.func_native(_FORWARD)
def _forward_rows(part: int, parts: int, width: int, height: int, image: _floats, target: _floats,
                  partials: _floats, row_sums: wp.array(dtype=wp.float64), l1_sums: wp.array(dtype=wp.float64),
                  scratch: _floats, scratch_floats: int): ...


@wp.func_native(_BACKWARD)
def _backward_rows(part: int, parts: int, width: int, height: int, partials: _floats, image: _floats,
                   target: _floats, scale: float, l1_scale: float, grad_image: _floats, scratch: _floats,
                   scratch_floats: int): ...


@wp.kernel
def _forward(offset: int, parts: int, width: int, height: int, image: _floats, target: _floats, partials: _floats,
             row_sums: wp.array(dtype=wp.float64), l1_sums: wp.array(dtype=wp.float64), scratch: _floats,
             scratch_floats: int):
    _forward_rows(offset + wp.tid(), parts, width, height, image, target, partials, row_sums, l1_sums, scratch,
                  scratch_floats)


@wp.kernel
def _backward(offset: int, parts: int, width: int, height: int, partials: _floats, image: _floats, target: _floats,
              grad_ssim: _floats, grad_l1: _floats, count: int, grad_image: _floats, scratch: _floats,
              scratch_floats: int):
    # The upstream gradients are read here, not on the host: each divided by the pixel count in double, then
    # rounded to float (what `float(grad) / count` handed over as a float argument gave).
    scale = wp.float32(wp.float64(grad_ssim[0]) / wp.float64(count))
    l1_scale = wp.float32(wp.float64(grad_l1[0]) / wp.float64(count))
    _backward_rows(offset + wp.tid(), parts, width, height, partials, image, target, scale, l1_scale, grad_image,
                   scratch, scratch_floats)


KERNELS = [_forward, _backward]
ROWS_PER_PART = 32  # fewer rows a thread would blur its range's 10 neighbouring rows along too often


def _parts(height: int) -> int:
    """The row ranges a pass is cut into: one per CPU thread, each at least ROWS_PER_PART rows."""
    return max(1, min(cpu_threads(), height // ROWS_PER_PART))


def forward_scratch_floats(width: int) -> int:
    """Floats of one part's room in the forward (_FORWARD): the ring of 5 maps, their padded rows, a row of the 5
    blurred statistics and of its similarity, and 5 rows of zeros."""
    return _WINDOW * 5 * width + 5 * (width + 2 * (_WINDOW // 2)) + 11 * width


def backward_scratch_floats(width: int) -> int:
    """Floats of one part's room in the backward (_BACKWARD): the ring of 3 maps, a padded row, a row of the 3
    blurred partials and 3 rows of zeros."""
    return _WINDOW * 3 * width + (width + 2 * (_WINDOW // 2)) + 6 * width


_flat = flat_view
_NO_GRADIENT = torch.zeros(1)  # the upstream gradient of an output the loss does not use


class _FusedSSIMAndL1(torch.autograd.Function):
    """(mean SSIM, mean |x - y|) of two float32 [H, W, 3] images: one read of the pixels for both, one gradient."""

    @staticmethod
    def forward(ctx, image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ensure_warp()
        height, width, _ = image.shape
        image, target = image.contiguous(), target.contiguous()  # no detach: grad mode is off in a forward
        partials = torch.empty(9, height, width)
        row_sums = torch.empty(height, dtype=torch.float64)
        l1_sums = torch.empty(height, dtype=torch.float64)
        parts = _parts(height)
        room = forward_scratch_floats(width)
        scratch = torch.empty(parts * room)
        run_ranges(_forward, parts, image.device, [parts, width, height, _flat(image), _flat(target), _flat(partials),
                                                   _flat(row_sums), _flat(l1_sums), _flat(scratch), room], 1)
        ctx.save_for_backward(image, target, partials)
        count = 3 * height * width
        return (row_sums.sum() / count).to(torch.float32), (l1_sums.sum() / count).to(torch.float32)

    @staticmethod
    def backward(ctx, grad_ssim: torch.Tensor | None, grad_l1: torch.Tensor | None):
        image, target, partials = ctx.saved_tensors
        height, width, _ = image.shape
        grad_image = torch.empty_like(image)
        upstream = [_NO_GRADIENT if g is None else g.contiguous() for g in (grad_ssim, grad_l1)]
        parts = _parts(height)
        room = backward_scratch_floats(width)
        scratch = torch.empty(parts * room)
        run_ranges(_backward, parts, image.device, [parts, width, height, _flat(partials), _flat(image),
                                                    _flat(target), *map(_flat, upstream), 3 * height * width,
                                                    _flat(grad_image), _flat(scratch), room], 1)
        return grad_image, None


def fused_ssim_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """True for float32 [H, W, 3] CPU images when no gradient is asked of the target."""
    return (image.device.type == "cpu" and image.dtype == torch.float32 and target.dtype == torch.float32
            and image.dim() == 3 and image.shape[-1] == 3 and image.shape == target.shape
            and not target.requires_grad)


def fused_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two float32 [H, W, 3] CPU images (losses.ssim), differentiable in `image`."""
    return _FusedSSIMAndL1.apply(image, target)[0]


def fused_ssim_and_l1(image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean SSIM, mean absolute difference) of two float32 [H, W, 3] CPU images, both differentiable in `image`:
    the photometric loss's two terms in one pass over the pixels forward and one backward."""
    return _FusedSSIMAndL1.apply(image, target)
