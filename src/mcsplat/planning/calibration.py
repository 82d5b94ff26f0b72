"""--budget's first measurements: steps of throwaway copies of the starting model, small and large, at full size and at
the starting size, timed before the clock starts, so that the first plan knows what pixels and Gaussians cost."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Iterator

import torch

from ..config import TrainConfig
from ..data import Scene
from ..gaussians import PARAM_KEYS, GaussianModel
from ..optim import make_optimizers
from .run_plan import Plan
from .planner import RunStep
from .strategy_choice import make_strategy

CALIBRATION_SMALL, CALIBRATION_LARGE = 2000, 3  # models of 2,000 and of 3x the starting Gaussians are timed


def timed_steps(config: TrainConfig, plan: Plan, model: GaussianModel, scene: Scene, step: RunStep,
                start: float) -> Iterator[tuple[float, int, float]]:
    """(seconds, Gaussians, share of the image size) of each timed step, at full size and at `start` (the size the
    run trains at first: at its current step when it resumes); the first step of each size is a warm-up and not
    counted. The run's own model and state are left as they are."""
    count = model.num_gaussians
    small, large = min(count, CALIBRATION_SMALL), CALIBRATION_LARGE * count
    for gaussians, scale in ((small, 1.0), (small, start), (count, 1.0), (large, 1.0), (large, start)):
        probe = replace(plan, resolution_start=scale, resolution_full_at=1.0, steps=10**9)
        copy = resized(model, gaussians)
        optimizers = make_optimizers(copy, probe.optim, scene.radius)
        strategy = make_strategy(config, probe, scene.radius, torch.Generator(step.device).manual_seed(0))
        on_copy = step.on(copy, optimizers, strategy)
        for i, view in enumerate(scene.train[:2]):
            tick = time.perf_counter()
            on_copy(0, view, probe).values.read()  # on a GPU: waits for the step's work, which is what is timed
            if i:  # the first is a warm-up
                yield time.perf_counter() - tick, copy.num_gaussians, scale


def resized(model: GaussianModel, count: int) -> GaussianModel:
    """A detached model of `count` Gaussians: the first `count` of `model`, or copies of it side by side."""
    copies = -(-count // max(model.num_gaussians, 1))
    resized = GaussianModel(*(torch.cat([model.params[key].detach()] * copies)[:count] for key in PARAM_KEYS))
    resized.antialiased = model.antialiased
    return resized
