"""Photometric losses of 3DGS: L1 and SSIM with an 11x11 Gaussian window (sigma 1.5), "same" padding (SPEC 3)."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


@functools.lru_cache(maxsize=8)
def _window(channels: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    coords = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    g = torch.exp(-coords ** 2 / (2 * SSIM_SIGMA ** 2))
    g = g / g.sum()
    window = (g[:, None] * g[None, :]).to(dtype=dtype, device=device)
    return window.expand(channels, 1, SSIM_WINDOW, SSIM_WINDOW).contiguous()


def ssim_map(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of two [H, W, C] images in [0, 1] -> [C, H, W]."""
    x = image.permute(2, 0, 1)[None]
    y = target.permute(2, 0, 1)[None]
    channels = x.shape[1]
    window = _window(channels, x.dtype, x.device)

    def blur(t):
        return F.conv2d(t, window, padding=SSIM_WINDOW // 2, groups=channels)

    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x ** 2
    var_y = blur(y * y) - mu_y ** 2
    cov = blur(x * y) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    denominator = (mu_x ** 2 + mu_y ** 2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (numerator / denominator)[0]


def ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two [H, W, C] images (the 3DGS definition)."""
    return ssim_map(image, target).mean()


def l1(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (image - target).abs().mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM), w = 0.2 as in 3DGS and the MCMC paper."""
    return (1.0 - ssim_weight) * l1(image, target) + ssim_weight * (1.0 - ssim(image, target))
