"""Fused SSIM for float32 images on the CPU: the mean SSIM of losses.py (and the L1 term beside it) with their
gradient, in one kernel forward and one backward.

torch's depthwise convolution is slow on the CPU (docs/measurements-log.md, "CPU kernels (rasterizer.py,
train_speed.py), 2026-11-22"); here the separable 11-tap Gaussian window runs as plain C++ loops over contiguous rows
that clang vectorises. With the windowed statistics mu_x, mu_y, <x^2>, <y^2>, <xy> of each pixel and channel,

    S = (2 mu_x mu_y + C1)(2 cov + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2)),

and since the zero-padded symmetric window is its own adjoint,

    d mean(S) / dx = [blur(dS/dmu_x) + 2 x blur(dS/d<x^2>) + y blur(dS/d<xy>)] / (3 H W).

Forward: each CPU thread takes a range of rows; for each channel it blurs the five statistics of a row along the row
into a ring of the last 11 rows, blurs them down the columns from the ring, and keeps S's three partial derivatives
(and each row's sums of S and of |x - y|). Backward: the same for the three partials, combined into the gradient
with L1's sign(x - y). The rows a range's window reaches beyond it are blurred by that range too, so every output
row is computed the same way whatever the threads (the result does not depend on them). Holding the row-blurred
rows in the ring instead of 15 full planes made the forward faster, and so did summing each blurred value's 11 taps
in a register, and the rows' sums in lanes outside the pixel loops (a running double sum kept clang from vectorising
the loop it sat in): docs/measurements-log.md, "The CPU loss fused with L1, the window sliding down each thread's
rows (train_speed.py, side by side), 2026-11-26" and "The CPU loss's blurs in registers; --budget's size never steps
back, 2026-11-27". CUDA and float64 keep the other paths of losses.py.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from ..compute.cpp_snippets import read_snippet
from ..compute.cpu_target import kernel_flags
from ..compute.runtime import cpu_threads, ensure_warp, flat_view, run_ranges, splits_small_work
from .warp import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW

# The window and constants are defined once, in ssim/warp.py.
_WINDOW, _SIGMA, _C1, _C2 = SSIM_WINDOW, SSIM_SIGMA, SSIM_C1, SSIM_C2


def _window() -> list[float]:
    weights = [math.exp(-(k - _WINDOW // 2) ** 2 / (2 * _SIGMA ** 2)) for k in range(_WINDOW)]
    total = sum(weights)
    return [w / total for w in weights]


_TAPS = ", ".join(f"{float(torch.tensor(w, dtype=torch.float32))!r}f" for w in _window())

# Each launch item is a range of output rows (one per CPU thread). A row's five statistics (or three partials) are
# blurred along the row once, into a ring of the last WINDOW rows, and blurred down the columns from there: the
# row-blurred planes never leave the thread's cache (the passes before wrote and read back 15 full planes). The C++
# is in ssim/cpu_helpers.h, ssim/cpu_forward.cpp and ssim/cpu_backward.cpp.
_HELPERS = read_snippet(__package__, "cpu_helpers.h", {
    "WINDOW": _WINDOW, "HALF_WINDOW": _WINDOW // 2, "TAP_LIST": "{" + _TAPS + "}"})
_FORWARD = read_snippet(__package__, "cpu_forward.cpp", {"HELPERS": _HELPERS, "C1": repr(_C1), "C2": repr(_C2)})
_BACKWARD = read_snippet(__package__, "cpu_backward.cpp", {"HELPERS": _HELPERS})

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
ROWS_PER_THREAD = 64  # and fewer a second thread's hand-off costs more than its rows save (a small step's image)


def _parts(height: int) -> int:
    """The row ranges a pass is cut into: one per CPU thread, each at least ROWS_PER_THREAD rows (ROWS_PER_PART
    where set_cpu_threads asks every thread to take a share of small work too)."""
    return max(1, min(cpu_threads(), height // (ROWS_PER_PART if splits_small_work() else ROWS_PER_THREAD)))


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
