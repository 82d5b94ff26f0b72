"""The SSIM of 3DGS (its window and constants) and a fused SSIM in plain Warp kernels, for CUDA first.

On CUDA, torch's separable depthwise convolutions take some forty launches forward + backward; these four launches take
a fraction of their GPU time (docs/measurements-log.md, "GPU: the tile kernels and the fused SSIM, 2026-11-26"). The
kernels are plain per-thread code (no native snippets, no tile API), so the same code runs on the CPU, where the tests
check it; training on the CPU keeps ssim/cpu.py, which is several times faster there.

With the windowed statistics mu_x, mu_y, <x^2>, <y^2>, <xy> of each pixel and channel,

    S = (2 mu_x mu_y + C1)(2 cov + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2)),

and since the zero-padded symmetric window is its own adjoint,

    d mean(S) / dx = [blur(dS/dmu_x) + 2 x blur(dS/d<x^2>) + y blur(dS/d<xy>)] / (3 H W).

Forward: (1) the five statistics blurred along the rows, (2) down the columns, then S and the three partial
derivatives per pixel and channel. Backward: (3) the partials blurred along the rows, (4) down the columns and
combined with x and y. One thread per pixel and channel; every output is written by one thread only, so the result
does not depend on timing, and the mean is a torch reduction of the S plane (no float atomics).
"""

from __future__ import annotations


import torch
import warp as wp

from ..compute.runtime import ensure_warp, launch_on_cuda, run_ranges, warp_view

# The 3DGS SSIM: an 11x11 Gaussian window of sigma 1.5, zero "same" padding (losses.py re-exports these).
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def window_taps() -> torch.Tensor:
    """The normalised 1D Gaussian window in float64 (the 2D window is its outer product with itself)."""
    coords = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    g = torch.exp(-coords ** 2 / (2 * SSIM_SIGMA ** 2))
    return g / g.sum()


# No kernel here is differentiated by Warp (the backward is written out): skip the adjoint code, half the compile.
wp.set_module_options({"enable_backward": False})

_WINDOW = wp.constant(SSIM_WINDOW)
_HALF = wp.constant(SSIM_WINDOW // 2)
# The taps compiled in (the float32 values torch's path uses): in the unrolled loops they are immediates, not loads.
_TAPS = wp.constant(wp.types.vector(length=SSIM_WINDOW, dtype=wp.float32)(*window_taps().float().tolist()))
_C1 = wp.constant(float(SSIM_C1))
_C2 = wp.constant(float(SSIM_C2))

# Threads go in tiles of 32 columns x 8 rows of one channel, one CUDA block each (see _pixel).
TILE_WIDTH, TILE_HEIGHT = 32, 8
_TILE_WIDTH = wp.constant(TILE_WIDTH)
_TILE_HEIGHT = wp.constant(TILE_HEIGHT)
_TILE_SIZE = wp.constant(TILE_WIDTH * TILE_HEIGHT)

_Image = wp.array3d(dtype=wp.float32)   # [H, W, 3], as the renderer writes it
_Planes = wp.array4d(dtype=wp.float32)  # [quantity, channel, H, W]: rows of one quantity are contiguous
_Scalar = wp.array(dtype=wp.float32)


@wp.func
def _pixel(index: int, height: int, width: int):
    """(channel, row, column) of a flat thread index: each run of 256 threads (a CUDA block) covers a tile of 32
    columns by 8 rows of one channel, so that a warp reads 32 neighbouring floats of a row and the column passes
    find rows their block has read already in its L1 cache. Indices past the image's edge in the last tiles give a
    row or column outside it."""
    tiles_across = (width + _TILE_WIDTH - 1) // _TILE_WIDTH
    tiles_per_channel = tiles_across * ((height + _TILE_HEIGHT - 1) // _TILE_HEIGHT)
    tile = index // _TILE_SIZE
    lane = index - tile * _TILE_SIZE
    channel = tile // tiles_per_channel
    tile_in_channel = tile - channel * tiles_per_channel
    tile_row = tile_in_channel // tiles_across
    tile_column = tile_in_channel - tile_row * tiles_across
    row = tile_row * _TILE_HEIGHT + lane // _TILE_WIDTH
    column = tile_column * _TILE_WIDTH + lane - (lane // _TILE_WIDTH) * _TILE_WIDTH
    return channel, row, column


# The blurs read a clamped neighbour with a zero weight outside the image (zero padding) rather than branching
# around the read: with an `if` per tap the compiler kept the reads in order, and the down-the-columns pass needed
# 118 registers and ran at a quarter of the occupancy, 6-8 times slower on an H100.
@wp.func
def _tap_inside(k: int, source: int, size: int):
    return wp.where((source >= 0) and (source < size), _TAPS[k], 0.0)


@wp.func
def _along_row(planes: _Planes, quantity: int, channel: int, row: int, column: int):
    width = planes.shape[3]
    total = float(0.0)
    for k in range(_WINDOW):
        source = column + k - _HALF
        total += _tap_inside(k, source, width) * planes[quantity, channel, row, wp.clamp(source, 0, width - 1)]
    return total


@wp.func
def _down_column(planes: _Planes, quantity: int, channel: int, row: int, column: int):
    height = planes.shape[2]
    total = float(0.0)
    for k in range(_WINDOW):
        source = row + k - _HALF
        total += _tap_inside(k, source, height) * planes[quantity, channel, wp.clamp(source, 0, height - 1), column]
    return total


@wp.kernel
def _statistics_along_rows(offset: int, image: _Image, target: _Image, rows: _Planes):
    """rows[s, c] = the s-th of x, y, x^2, y^2, xy of channel c, blurred along the rows."""
    height, width = image.shape[0], image.shape[1]
    channel, row, column = _pixel(offset + wp.tid(), height, width)
    if row >= height or column >= width:
        return
    sum_x = float(0.0)
    sum_y = float(0.0)
    sum_xx = float(0.0)
    sum_yy = float(0.0)
    sum_xy = float(0.0)
    for k in range(_WINDOW):
        source = column + k - _HALF
        weight = _tap_inside(k, source, width)
        clamped = wp.clamp(source, 0, width - 1)
        x = image[row, clamped, channel]
        y = target[row, clamped, channel]
        sum_x += weight * x
        sum_y += weight * y
        sum_xx += weight * x * x
        sum_yy += weight * y * y
        sum_xy += weight * x * y
    rows[0, channel, row, column] = sum_x
    rows[1, channel, row, column] = sum_y
    rows[2, channel, row, column] = sum_xx
    rows[3, channel, row, column] = sum_yy
    rows[4, channel, row, column] = sum_xy


@wp.func
def _statistics_down_columns(rows: _Planes, channel: int, row: int, column: int):
    """mu_x, mu_y, <x^2>, <y^2>, <xy>: the statistics blurred along the rows (rows[0..4, c]), now down the columns."""
    return (_down_column(rows, 0, channel, row, column), _down_column(rows, 1, channel, row, column),
            _down_column(rows, 2, channel, row, column), _down_column(rows, 3, channel, row, column),
            _down_column(rows, 4, channel, row, column))


@wp.func
def _partials_down_columns(rows: _Planes, channel: int, row: int, column: int):
    """The partials by mu_x, <x^2> and <xy> blurred along the rows (rows[0..2, c]), now down the columns."""
    return (_down_column(rows, 0, channel, row, column), _down_column(rows, 1, channel, row, column),
            _down_column(rows, 2, channel, row, column))


@wp.kernel
def _ssim_down_columns(offset: int, rows: _Planes, partials: _Planes):
    """S of each pixel and channel (into rows[5, c], beside the statistics it comes from), and its partial
    derivatives by mu_x, <x^2> and <xy> (partials[0..2, c])."""
    height, width = rows.shape[2], rows.shape[3]
    channel, row, column = _pixel(offset + wp.tid(), height, width)
    if row >= height or column >= width:
        return
    mu_x, mu_y, mean_xx, mean_yy, mean_xy = _statistics_down_columns(rows, channel, row, column)
    var_x = mean_xx - mu_x * mu_x
    var_y = mean_yy - mu_y * mu_y
    cov = mean_xy - mu_x * mu_y
    luminance_num = 2.0 * mu_x * mu_y + _C1
    structure_num = 2.0 * cov + _C2
    luminance_den = mu_x * mu_x + mu_y * mu_y + _C1
    structure_den = var_x + var_y + _C2
    inverse = 1.0 / (luminance_den * structure_den)
    s = luminance_num * structure_num * inverse
    rows[5, channel, row, column] = s
    # mu_x enters all four factors (cov and var_x through -mu_x mu_y and -mu_x^2); <x^2> only var_x; <xy> only cov.
    partials[0, channel, row, column] = (2.0 * mu_y * (structure_num - luminance_num) * inverse
                                         - 2.0 * s * mu_x / luminance_den + 2.0 * s * mu_x / structure_den)
    partials[1, channel, row, column] = -s / structure_den
    partials[2, channel, row, column] = 2.0 * luminance_num * inverse


@wp.kernel
def _partials_along_rows(offset: int, partials: _Planes, rows: _Planes):
    height, width = partials.shape[2], partials.shape[3]
    channel, row, column = _pixel(offset + wp.tid(), height, width)
    if row >= height or column >= width:
        return
    for quantity in range(3):
        rows[quantity, channel, row, column] = _along_row(partials, quantity, channel, row, column)


@wp.kernel
def _gradient_down_columns(offset: int, rows: _Planes, image: _Image, target: _Image, grad_output: _Scalar,
                           inverse_count: float, grad_image: _Image):
    height, width = rows.shape[2], rows.shape[3]
    channel, row, column = _pixel(offset + wp.tid(), height, width)
    if row >= height or column >= width:
        return
    d_mu, d_xx, d_xy = _partials_down_columns(rows, channel, row, column)
    x = image[row, column, channel]
    y = target[row, column, channel]
    # grad_output is read on the device: converting it to a Python float would wait for the GPU.
    grad_image[row, column, channel] = grad_output[0] * inverse_count * (d_mu + 2.0 * x * d_xx + y * d_xy)


KERNELS = [_statistics_along_rows, _ssim_down_columns, _partials_along_rows, _gradient_down_columns]
for _kernel in KERNELS:
    _kernel.launch_block_dim = TILE_WIDTH * TILE_HEIGHT  # compute/compile.py builds them for the block size launched

def _launch(kernel, height: int, width: int, device: torch.device, arguments: list) -> None:
    """One thread per pixel and channel, in tiles of 32 x 8 (see _pixel): on CUDA one launch on torch's current
    stream, a block per tile; on the CPU ranges of threads from the thread pool."""
    tiles = -(-width // TILE_WIDTH) * -(-height // TILE_HEIGHT)
    n = 3 * tiles * TILE_WIDTH * TILE_HEIGHT
    if device.type == "cuda":
        launch_on_cuda(kernel, n, [0] + arguments, device, block_dim=TILE_WIDTH * TILE_HEIGHT)
    else:
        run_ranges(kernel, n, device, arguments)


def _planes(count: int, height: int, width: int, device: torch.device) -> torch.Tensor:
    return torch.empty(count, 3, height, width, dtype=torch.float32, device=device)


class _FusedSSIMWarp(torch.autograd.Function):
    # At training sizes the Python work around the launches (Warp views, launches, allocations) costs more than the
    # kernels on the GPU, so the views made in forward are kept for backward.

    @staticmethod
    def forward(ctx, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        ensure_warp()
        height, width, _ = image.shape
        image, target = image.detach().contiguous(), target.detach().contiguous()
        device = image.device
        rows = _planes(6, height, width, device)  # the five statistics blurred along the rows, then S
        partials = _planes(3, height, width, device)
        views = warp_view(image), warp_view(target), warp_view(partials)
        rows_view = warp_view(rows)
        _launch(_statistics_along_rows, height, width, device, [views[0], views[1], rows_view])
        _launch(_ssim_down_columns, height, width, device, [rows_view, views[2]])
        ctx.save_for_backward(image, target, partials)  # (checks that nothing wrote to them before backward)
        ctx.views = views
        return rows[5].mean()

    @staticmethod
    def backward(ctx, grad_output: torch.Tensor):
        image, _, _ = ctx.saved_tensors
        image_view, target_view, partials_view = ctx.views
        height, width, _ = image.shape
        device = image.device
        rows = warp_view(_planes(3, height, width, device))
        grad_image = torch.empty_like(image)
        _launch(_partials_along_rows, height, width, device, [partials_view, rows])
        _launch(_gradient_down_columns, height, width, device,
                [rows, image_view, target_view, warp_view(grad_output.reshape(1)), 1.0 / image.numel(),
                 warp_view(grad_image)])
        return grad_image, None


def fused_ssim_warp_applies(image: torch.Tensor, target: torch.Tensor) -> bool:
    """True for float32 [H, W, 3] CUDA images when no gradient is asked of the target (losses.ssim's CUDA path)."""
    return (image.device.type == "cuda" and target.device == image.device and image.dtype == torch.float32
            and target.dtype == torch.float32 and image.dim() == 3 and image.shape[-1] == 3
            and image.shape == target.shape and not target.requires_grad)


def fused_ssim_warp(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two float32 [H, W, 3] images on any device (losses.ssim), differentiable in `image` only."""
    if image.dtype != torch.float32 or target.dtype != torch.float32:
        raise TypeError(f"fused_ssim_warp takes float32 images, got {image.dtype} and {target.dtype}")
    if image.dim() != 3 or image.shape[-1] != 3 or image.shape != target.shape:
        raise ValueError(f"fused_ssim_warp takes two [H, W, 3] images, got {tuple(image.shape)} and "
                         f"{tuple(target.shape)}")
    return _FusedSSIMWarp.apply(image, target)
