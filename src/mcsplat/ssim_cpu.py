"""Fused SSIM for float32 images on the CPU: the mean SSIM of losses.py and its gradient in four row passes.

torch's depthwise convolution is slow on the CPU (the loss took 40-60 ms of a 400x400 training step); here the
separable 11-tap Gaussian window runs as plain C++ loops over contiguous rows that clang vectorises. With the
windowed statistics mu_x, mu_y, <x^2>, <y^2>, <xy> of each pixel and channel,

    S = (2 mu_x mu_y + C1)(2 cov + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2)),

and since the zero-padded symmetric window is its own adjoint,

    d mean(S) / dx = [blur(dS/dmu_x) + 2 x blur(dS/d<x^2>) + y blur(dS/d<xy>)] / (3 H W).

Forward: (1) the five statistics of each row, blurred along the row; (2) blurred down the columns, S summed per row
and the three partial derivatives kept. Backward: (3) the partials blurred along the rows, (4) down the columns and
combined. Each pass is one Warp launch over rows (ranges of rows per CPU thread; every output row is written by one
thread only, so the result does not depend on timing). CUDA and float64 keep the torch version of losses.py.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from .compute.runtime import ensure_warp, run_ranges
from .ssim_warp import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW

# The window and constants are defined once, in ssim_warp.py.
_WINDOW, _SIGMA, _C1, _C2 = SSIM_WINDOW, SSIM_SIGMA, SSIM_C1, SSIM_C2


def _window() -> list[float]:
    weights = [math.exp(-(k - _WINDOW // 2) ** 2 / (2 * _SIGMA ** 2)) for k in range(_WINDOW)]
    total = sum(weights)
    return [w / total for w in weights]


_TAPS = ", ".join(f"{float(torch.tensor(w, dtype=torch.float32))!r}f" for w in _window())

# Blurs helpers shared by the passes: along a row (zero padding at both ends) and down the columns (rows outside
# the image count as zero).
_HELPERS = f"""
    const float taps[{_WINDOW}] = {{{_TAPS}}};
    const int half = {_WINDOW // 2};
    const int w = width, h = height;
    float* padded = (float*)__builtin_alloca(sizeof(float) * (w + 2 * half));
    for (int j = 0; j < half; ++j) {{ padded[j] = 0.0f; padded[w + half + j] = 0.0f; }}
    auto blur_row = [&](float* out) {{  // padded[half .. half + w) -> out[0 .. w)
        for (int j = 0; j < w; ++j) {{
            float sum = 0.0f;
            for (int k = 0; k < {_WINDOW}; ++k) sum += taps[k] * padded[j + k];
            out[j] = sum;
        }}
    }};
    auto blur_column = [&](const float* plane, float* out) {{  // rows row - half .. row + half of plane -> out
        for (int j = 0; j < w; ++j) out[j] = 0.0f;
        for (int k = 0; k < {_WINDOW}; ++k) {{
            const int source = row + k - half;
            if (source < 0 || source >= h) continue;
            const float* in = plane + (long)source * w;
            const float weight = taps[k];
            for (int j = 0; j < w; ++j) out[j] += weight * in[j];
        }}
    }};
    const long plane = (long)w * h;
"""

_STATISTICS_ALONG_ROWS = _HELPERS + """
    const float* x = (const float*)image.data + (long)row * w * 3;
    const float* y = (const float*)target.data + (long)row * w * 3;
    float* out = (float*)blurred.data;
    for (int c = 0; c < 3; ++c) {
        for (int s = 0; s < 5; ++s) {
            for (int j = 0; j < w; ++j) {
                const float xv = x[3 * j + c], yv = y[3 * j + c];
                padded[half + j] = s == 0 ? xv : s == 1 ? yv : s == 2 ? xv * xv : s == 3 ? yv * yv : xv * yv;
            }
            blur_row(out + (s * 3 + c) * plane + (long)row * w);
        }
    }
"""

_SSIM_DOWN_COLUMNS = _HELPERS + f"""
    const float* in = (const float*)blurred.data;
    float* partial = (float*)partials.data;
    float* stat[5];
    for (int s = 0; s < 5; ++s) stat[s] = (float*)__builtin_alloca(sizeof(float) * w);
    double total = 0.0;
    for (int c = 0; c < 3; ++c) {{
        for (int s = 0; s < 5; ++s) blur_column(in + (s * 3 + c) * plane, stat[s]);
        float* d_mu = partial + (0 * 3 + c) * plane + (long)row * w;
        float* d_xx = partial + (1 * 3 + c) * plane + (long)row * w;
        float* d_xy = partial + (2 * 3 + c) * plane + (long)row * w;
        for (int j = 0; j < w; ++j) {{
            const float mx = stat[0][j], my = stat[1][j];
            const float var_x = stat[2][j] - mx * mx, var_y = stat[3][j] - my * my, cov = stat[4][j] - mx * my;
            const float a = 2.0f * mx * my + {_C1!r}f, b = 2.0f * cov + {_C2!r}f;
            const float cc = mx * mx + my * my + {_C1!r}f, d = var_x + var_y + {_C2!r}f;
            const float inv = 1.0f / (cc * d);
            const float s = a * b * inv;
            total += s;
            d_mu[j] = 2.0f * my * (b - a) * inv - 2.0f * s * mx / cc + 2.0f * s * mx / d;
            d_xx[j] = -s / d;
            d_xy[j] = 2.0f * a * inv;
        }}
    }}
    ((double*)row_sums.data)[row] = total;
"""

_PARTIALS_ALONG_ROWS = _HELPERS + """
    const float* in = (const float*)partials.data;
    float* out = (float*)blurred.data;
    for (int m = 0; m < 9; ++m) {
        const float* source = in + m * plane + (long)row * w;
        for (int j = 0; j < w; ++j) padded[half + j] = source[j];
        blur_row(out + m * plane + (long)row * w);
    }
"""

_GRADIENT_DOWN_COLUMNS = _HELPERS + """
    const float* in = (const float*)blurred.data;
    const float* x = (const float*)image.data + (long)row * w * 3;
    const float* y = (const float*)target.data + (long)row * w * 3;
    float* grad = (float*)grad_image.data + (long)row * w * 3;
    float* b[3];
    for (int q = 0; q < 3; ++q) b[q] = (float*)__builtin_alloca(sizeof(float) * w);
    for (int c = 0; c < 3; ++c) {
        for (int q = 0; q < 3; ++q) blur_column(in + (q * 3 + c) * plane, b[q]);
        for (int j = 0; j < w; ++j)
            grad[3 * j + c] = scale * (b[0][j] + 2.0f * x[3 * j + c] * b[1][j] + y[3 * j + c] * b[2][j]);
    }
"""

# Fused multiply-add in the blur loops (Warp's default keeps a * b + c as two roundings).
wp.set_module_options({"cpu_compiler_flags": "-march=native -ffp-contract=fast"})

_floats = wp.array(dtype=wp.float32)


@wp.func_native(_STATISTICS_ALONG_ROWS)
def _statistics_along_rows(row: int, width: int, height: int, image: _floats, target: _floats, blurred: _floats): ...


@wp.func_native(_SSIM_DOWN_COLUMNS)
def _ssim_down_columns(row: int, width: int, height: int, blurred: _floats, partials: _floats,
                       row_sums: wp.array(dtype=wp.float64)): ...


@wp.func_native(_PARTIALS_ALONG_ROWS)
def _partials_along_rows(row: int, width: int, height: int, partials: _floats, blurred: _floats): ...


@wp.func_native(_GRADIENT_DOWN_COLUMNS)
def _gradient_down_columns(row: int, width: int, height: int, blurred: _floats, image: _floats, target: _floats,
                           scale: float, grad_image: _floats): ...


@wp.kernel
def _pass1(offset: int, width: int, height: int, image: _floats, target: _floats, blurred: _floats):
    _statistics_along_rows(offset + wp.tid(), width, height, image, target, blurred)


@wp.kernel
def _pass2(offset: int, width: int, height: int, blurred: _floats, partials: _floats,
           row_sums: wp.array(dtype=wp.float64)):
    _ssim_down_columns(offset + wp.tid(), width, height, blurred, partials, row_sums)


@wp.kernel
def _pass3(offset: int, width: int, height: int, partials: _floats, blurred: _floats):
    _partials_along_rows(offset + wp.tid(), width, height, partials, blurred)


@wp.kernel
def _pass4(offset: int, width: int, height: int, blurred: _floats, image: _floats, target: _floats, scale: float,
           grad_image: _floats):
    _gradient_down_columns(offset + wp.tid(), width, height, blurred, image, target, scale, grad_image)


def _flat(tensor: torch.Tensor):
    return wp.from_torch(tensor.reshape(-1), requires_grad=False)


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        ensure_warp()
        height, width, _ = image.shape
        image, target = image.detach().contiguous(), target.detach().contiguous()
        blurred = torch.empty(15, height, width)
        partials = torch.empty(9, height, width)
        row_sums = torch.empty(height, dtype=torch.float64)
        device = image.device
        run_ranges(_pass1, height, device, [width, height, _flat(image), _flat(target), _flat(blurred)], 16)
        run_ranges(_pass2, height, device, [width, height, _flat(blurred), _flat(partials), _flat(row_sums)], 16)
        ctx.save_for_backward(image, target, partials)
        return (row_sums.sum() / (3 * height * width)).to(torch.float32)

    @staticmethod
    def backward(ctx, grad_output: torch.Tensor):
        image, target, partials = ctx.saved_tensors
        height, width, _ = image.shape
        blurred = torch.empty(9, height, width)
        grad_image = torch.empty_like(image)
        scale = float(grad_output) / (3 * height * width)
        run_ranges(_pass3, height, image.device, [width, height, _flat(partials), _flat(blurred)], 16)
        run_ranges(_pass4, height, image.device, [width, height, _flat(blurred), _flat(image), _flat(target), scale,
                                                  _flat(grad_image)], 16)
        return grad_image, None


def fused_ssim_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """True for float32 [H, W, 3] CPU images when no gradient is asked of the target."""
    return (image.device.type == "cpu" and image.dtype == torch.float32 and target.dtype == torch.float32
            and image.dim() == 3 and image.shape[-1] == 3 and image.shape == target.shape
            and not target.requires_grad)


def fused_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two float32 [H, W, 3] CPU images (losses.ssim), differentiable in `image`."""
    return _FusedSSIM.apply(image, target)
