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
rows in the ring instead of 15 full planes halved the forward's time at 800x600. CUDA and float64 keep the other
paths of losses.py.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from .compute.runtime import cpu_threads, ensure_warp, run_ranges
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
    auto blur_row = [&](const float* padded, float* out) {{  // padded[0 .. w + 2 half) -> out[0 .. w)
        for (int j = 0; j < w; ++j) out[j] = taps[0] * padded[j];
        for (int k = 1; k < window; ++k) {{
            const float weight = taps[k];
            const float* in = padded + k;
            for (int j = 0; j < w; ++j) out[j] += weight * in[j];
        }}
    }};
    // The rows of the window around `row` inside the image, blurred down the columns from the ring (maps of w).
    auto blur_column = [&](const float* ring, int maps, int row, float* out) {{
        for (int j = 0; j < maps * w; ++j) out[j] = 0.0f;
        for (int k = 0; k < window; ++k) {{
            const int source = row + k - half;
            if (source < 0 || source >= h) continue;
            const float* in = ring + (long)(source % window) * maps * w;
            const float weight = taps[k];
            for (int j = 0; j < maps * w; ++j) out[j] += weight * in[j];
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
    // On the heap: the ring of a 4K image's rows (845 KB) is more than some platforms give a thread's stack.
    float* ring = (float*)malloc(sizeof(float) * (window * 5 * w + 5 * stride + 5 * w));
    float* padded = ring + window * 5 * w;
    float* stat = padded + 5 * stride;
    for (int s = 0; s < 5; ++s)
        for (int j = 0; j < half; ++j) padded[s * stride + j] = padded[s * stride + half + w + j] = 0.0f;
    for (int row = first; row < last; ++row) {{
        sums[row] = 0.0;
        double difference = 0.0;  // the L1 loss's share of the row, read while the pixels are at hand
        const float* xr = x + (long)row * w * 3;
        const float* yr = y + (long)row * w * 3;
        for (int j = 0; j < 3 * w; ++j) difference += fabsf(xr[j] - yr[j]);
        l1[row] = difference;
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
            blur_column(ring, 5, row, stat);
            float* d_mu = partial + (0 * 3 + c) * plane + (long)row * w;
            float* d_xx = partial + (1 * 3 + c) * plane + (long)row * w;
            float* d_xy = partial + (2 * 3 + c) * plane + (long)row * w;
            double total = 0.0;
            for (int j = 0; j < w; ++j) {{
                const float mx = stat[j], my = stat[w + j];
                const float var_x = stat[2 * w + j] - mx * mx, var_y = stat[3 * w + j] - my * my;
                const float cov = stat[4 * w + j] - mx * my;
                const float a = 2.0f * mx * my + {_C1!r}f, b = 2.0f * cov + {_C2!r}f;
                const float cc = mx * mx + my * my + {_C1!r}f, d = var_x + var_y + {_C2!r}f;
                const float inv = 1.0f / (cc * d);
                const float s = a * b * inv;
                total += s;
                d_mu[j] = 2.0f * my * (b - a) * inv - 2.0f * s * mx / cc + 2.0f * s * mx / d;
                d_xx[j] = -s / d;
                d_xy[j] = 2.0f * a * inv;
            }}
            sums[row] += total;
        }}
    }}
    free(ring);
"""

_BACKWARD = _HELPERS + """
    const float* in = (const float*)partials.data;
    const float* x = (const float*)image.data;
    const float* y = (const float*)target.data;
    float* grad = (float*)grad_image.data;
    const int stride = w + 2 * half;
    float* ring = (float*)malloc(sizeof(float) * (window * 3 * w + stride + 3 * w));
    float* padded = ring + window * 3 * w;
    float* b = padded + stride;
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
            blur_column(ring, 3, row, b);
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
    free(ring);
"""

# Fused multiply-add in the blur loops (Warp's default keeps a * b + c as two roundings).
wp.set_module_options({"cpu_compiler_flags": "-march=native -ffp-contract=fast"})

_floats = wp.array(dtype=wp.float32)


@wp.func_native(_FORWARD)
def _forward_rows(part: int, parts: int, width: int, height: int, image: _floats, target: _floats,
                  partials: _floats, row_sums: wp.array(dtype=wp.float64), l1_sums: wp.array(dtype=wp.float64)): ...


@wp.func_native(_BACKWARD)
def _backward_rows(part: int, parts: int, width: int, height: int, partials: _floats, image: _floats,
                   target: _floats, scale: float, l1_scale: float, grad_image: _floats): ...


@wp.kernel
def _forward(offset: int, parts: int, width: int, height: int, image: _floats, target: _floats, partials: _floats,
             row_sums: wp.array(dtype=wp.float64), l1_sums: wp.array(dtype=wp.float64)):
    _forward_rows(offset + wp.tid(), parts, width, height, image, target, partials, row_sums, l1_sums)


@wp.kernel
def _backward(offset: int, parts: int, width: int, height: int, partials: _floats, image: _floats, target: _floats,
              scale: float, l1_scale: float, grad_image: _floats):
    _backward_rows(offset + wp.tid(), parts, width, height, partials, image, target, scale, l1_scale, grad_image)


KERNELS = [_forward, _backward]
ROWS_PER_PART = 32  # fewer rows a thread would blur its range's 10 neighbouring rows along too often


def _parts(height: int) -> int:
    """The row ranges a pass is cut into: one per CPU thread, each at least ROWS_PER_PART rows."""
    return max(1, min(cpu_threads(), height // ROWS_PER_PART))


def _flat(tensor: torch.Tensor):
    return wp.from_torch(tensor.reshape(-1), requires_grad=False)


class _FusedSSIMAndL1(torch.autograd.Function):
    """(mean SSIM, mean |x - y|) of two float32 [H, W, 3] images: one read of the pixels for both, one gradient."""

    @staticmethod
    def forward(ctx, image: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        ensure_warp()
        height, width, _ = image.shape
        image, target = image.detach().contiguous(), target.detach().contiguous()
        partials = torch.empty(9, height, width)
        row_sums = torch.empty(height, dtype=torch.float64)
        l1_sums = torch.empty(height, dtype=torch.float64)
        parts = _parts(height)
        run_ranges(_forward, parts, image.device, [parts, width, height, _flat(image), _flat(target), _flat(partials),
                                                   _flat(row_sums), _flat(l1_sums)], 1)
        ctx.save_for_backward(image, target, partials)
        count = 3 * height * width
        return (row_sums.sum() / count).to(torch.float32), (l1_sums.sum() / count).to(torch.float32)

    @staticmethod
    def backward(ctx, grad_ssim: torch.Tensor | None, grad_l1: torch.Tensor | None):
        image, target, partials = ctx.saved_tensors
        height, width, _ = image.shape
        grad_image = torch.empty_like(image)
        count = 3 * height * width
        scale = 0.0 if grad_ssim is None else float(grad_ssim) / count
        l1_scale = 0.0 if grad_l1 is None else float(grad_l1) / count
        parts = _parts(height)
        run_ranges(_backward, parts, image.device, [parts, width, height, _flat(partials), _flat(image),
                                                    _flat(target), scale, l1_scale, _flat(grad_image)], 1)
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
