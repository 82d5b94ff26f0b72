"""The strategy a run's configuration names, refining on its plan's schedule."""

from __future__ import annotations

import torch

from ..config import TrainConfig
from ..strategy import ADCStrategy, MCMCStrategy, Strategy
from .run_plan import Plan


def make_strategy(config: TrainConfig, plan: Plan, scene_radius: float, generator: torch.Generator,
                  image_pixels: int | None = None, white_background: bool = False) -> Strategy:
    """image_pixels (a training image's, the median over them): the ceiling of MCMC's automatic cap;
    white_background: ADC's reset at its first densification step (3DGS's rule)."""
    if config.strategy == "mcmc":
        return MCMCStrategy(config.mcmc, scene_radius, generator, image_pixels, schedule=plan.schedule)
    return ADCStrategy(config.adc, scene_radius, generator, white_background, schedule=plan.schedule)
