"""Photometric losses of 3DGS: L1 and SSIM with an 11x11 Gaussian window (sigma 1.5), "same" padding.

The SSIM's window and constants live in ssim/warp.py (the fused kernels need them and may not import this module);
they are re-exported here."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from .ssim.cpu import fused_ssim, fused_ssim_and_l1, fused_ssim_applies
from .ssim.warp import KERNELS as WARP_SSIM_KERNELS
from .ssim.warp import SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW  # noqa: F401  (defined there, used as losses.SSIM_*)
from .ssim.warp import fused_ssim_warp, fused_ssim_warp_applies, window_taps


@functools.lru_cache(maxsize=8)
def _window_1d(channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return window_taps().to(dtype=dtype, device=device).expand(channels, 1, SSIM_WINDOW).contiguous()


def gaussian_blur(t: torch.Tensor) -> torch.Tensor:
    """The 11x11 Gaussian window with zero padding, as two 1D passes (exact: the window is an outer product)."""
    channels = t.shape[1]
    g = _window_1d(channels, t.dtype, t.device)
    half = SSIM_WINDOW // 2
    t = F.conv2d(t, g[:, :, :, None], padding=(half, 0), groups=channels)
    return F.conv2d(t, g[:, :, None, :], padding=(0, half), groups=channels)


def ssim_map(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two [H, W, C] images in [0, 1] -> [C, H, W]."""
    x = image.permute(2, 0, 1)[None]
    y = target.permute(2, 0, 1)[None]
    # One blur for the five local statistics.
    stats = gaussian_blur(torch.cat([x, y, x * x, y * y, x * y], dim=1))
    mu_x, mu_y, xx, yy, xy = stats.chunk(5, dim=1)
    var_x = xx - mu_x ** 2
    var_y = yy - mu_y ** 2
    cov = xy - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    denominator = (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (numerator / denominator)[0]


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images (the 3DGS definition). float32 RGB takes fused kernels with the same value
    and gradient, several times faster than torch's depthwise convolutions: ssim/cpu.py on the CPU, the Warp kernels
    of ssim/warp.py on CUDA."""
    if fused_ssim_applies(image, target):
        return fused_ssim(image, target)
    if fused_ssim_warp_applies(image, target):
        return fused_ssim_warp(image, target)
    return ssim_map(image, target).mean()


def training_kernels(device: torch.device, dtype: torch.dtype = torch.float32) -> list:
    """The Warp kernels the loss and its backward launch on `device` (the fused SSIM: float32 on the CPU or CUDA)."""
    if dtype != torch.float32:
        return []
    if device.type == "cpu":
        from .ssim import cpu as ssim_cpu
        return list(ssim_cpu.KERNELS)
    if device.type == "cuda":
        return list(WARP_SSIM_KERNELS)
    return []


def l1(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (image - target).abs().mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM), w = 0.2 as in 3DGS and the MCMC paper (on the CPU both terms from one fused pass)."""
    if fused_ssim_applies(image, target):
        similarity, difference = fused_ssim_and_l1(image, target)
        return (1.0 - ssim_weight) * difference + ssim_weight * (1.0 - similarity)
    return (1.0 - ssim_weight) * l1(image, target) + ssim_weight * (1.0 - ssim(image, target))


def masked_photometric_loss(image: torch.Tensor, target: torch.Tensor, keep: torch.Tensor | None,
                            ssim_weight: float = 0.2) -> torch.Tensor:
    """photometric_loss over the pixels a mask keeps (`keep`: [H, W, 1] weights in [0, 1], None: every pixel).

    Where a pixel is left out, the render and the target both take the render's own detached value: the pixel adds
    no L1, SSIM windows that reach it see no difference there, and no gradient reaches the render through it. The
    loss is divided by the kept share, so that it keeps its weight against the strategy's regularizers."""
    if keep is None:
        return photometric_loss(image, target, ssim_weight)
    fixed = image.detach()
    left_out = 1.0 - keep
    image = image * keep + fixed * left_out
    target = target * keep + fixed * left_out
    return photometric_loss(image, target, ssim_weight) / keep.mean().clamp_min(1e-6)
