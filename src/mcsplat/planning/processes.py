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

import math
from dataclasses import replace

from .run_plan import Plan

LEARNING_RATES = ("means_lr", "means_lr_final", "sh0_lr", "shN_lr", "opacity_lr", "scales_lr", "quats_lr")


def for_processes(plan: Plan, world_size: int) -> Plan:
    """`plan` for `world_size` processes (the plan itself when there is one)."""
    if world_size == 1:
        return plan
    optim, factor = plan.optim, math.sqrt(world_size)
    rates = {name: getattr(optim, name) * factor for name in LEARNING_RATES}
    scaled_optim = replace(optim, **rates, eps=optim.eps / factor,
                           betas=tuple(max(0.0, 1.0 - world_size * (1.0 - beta)) for beta in optim.betas))
    return replace(plan.scaled(1, world_size), steps=math.ceil(plan.steps / world_size),  # at least the
                   optim=scaled_optim, world_size=world_size)                                     # views asked for
