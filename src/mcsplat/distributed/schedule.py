"""N processes train with N views per step: the learning rates and step schedules that keep one run's meaning.

The rule (the one gsplat and Grendel use for a batch of N views, from Grendel's analysis, arXiv 2402.18824): every
learning rate x sqrt(N), Adam's epsilon / sqrt(N) and its betas 1 - N (1 - beta) (the moments forget as fast per
view seen), and every step count (the steps, the refine / densify / opacity-reset schedules, the SH degree increase)
/ N, so that the run sees the same number of views and refines at the same points of it. The position
learning-rate decay follows the steps.
The MCMC noise scales with the position learning rate (x sqrt(N)) while it is added N times less often, so the
variance it adds over the run is unchanged.
"""

from __future__ import annotations

import copy
import math

from ..config import TrainConfig
from ..schedule import scale_step_schedules

LEARNING_RATES = ("means_lr", "means_lr_final", "sh0_lr", "shN_lr", "opacity_lr", "scales_lr", "quats_lr")


def scaled_for_processes(config: TrainConfig, world_size: int) -> TrainConfig:
    """A copy of `config` for `world_size` processes (config itself when there is one), with world_size recorded."""
    if world_size == 1:
        return config
    scaled = copy.deepcopy(config)
    scaled.world_size = world_size
    scaled.steps = math.ceil(config.steps / world_size)  # at least the views asked for
    scale_step_schedules(scaled, 1, world_size)
    factor = math.sqrt(world_size)
    for name in LEARNING_RATES:
        setattr(scaled.optim, name, getattr(config.optim, name) * factor)
    scaled.optim.eps = config.optim.eps / factor
    scaled.optim.betas = tuple(max(0.0, 1.0 - world_size * (1.0 - beta)) for beta in config.optim.betas)
    return scaled
