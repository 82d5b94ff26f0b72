"""Densification strategies behind one protocol: MCMC (the paper) and ADC (the 3DGS baseline)."""

import torch

from . import position_noise_simd, screen_gradients
from .adc import ADCConfig, ADCSchedule, ADCStrategy
from .base import Strategy
from .mcmc import MCMCConfig, MCMCSchedule, MCMCStrategy

__all__ = ["Strategy", "MCMCConfig", "MCMCSchedule", "MCMCStrategy", "ADCConfig", "ADCSchedule", "ADCStrategy",
           "training_kernels"]


def training_kernels(device: torch.device) -> list:
    """The Warp kernels the strategies launch in a training step on `device` (compiled before the first step): the
    CPU's noise and screen-gradient loops (on CUDA they are torch operators)."""
    if torch.device(device).type != "cpu":
        return []
    return [*position_noise_simd.KERNELS, screen_gradients.add_norms_cpu]
