"""The seam between the training loop and its planner: what the loop asks of a planner (Planner: fixed.py's and
budget.py's), and what a planner sees of the run (its state, its step). The planners sit below the loop (see
docs/architecture.md), so the loop hands its state and its step down."""

from __future__ import annotations

from typing import Any, Protocol

import torch

from ..data import Scene
from ..gaussians import GaussianModel
from ..strategy import Strategy
from .run_plan import Plan

Background = tuple[float, float, float]


class RunState(Protocol):
    """What a planner sees of the run's state (state.TrainingState)."""

    model: GaussianModel
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: Strategy
    step: int
    wall_seconds: float


class RunStep(Protocol):
    """step.Step: the run's optimisation step, and the same step on another model."""

    device: torch.device
    background: Background

    def __call__(self, step: int, view: Any, plan: Plan, view_index: int = 0) -> Any:
        ...

    def on(self, model: GaussianModel, optimizers: dict, strategy: Any) -> RunStep:
        ...


class Planner(Protocol):
    """What the loop asks of a planner, whichever made the plan."""

    plan: Plan  # as it stands: the step and the strategy follow it
    budget_seconds: float | None  # --budget's time (metrics.json has it), or None

    def begin(self, state: RunState, scene: Scene, step: RunStep) -> None:
        """Before the first step (--budget: time a few steps and make the first plan)."""
        ...

    def after_step(self, seconds: float, gaussians: int, scale: float, *, step: int, wall_seconds: float,
                   gaussians_now: int) -> None:
        """A step of `seconds` with `gaussians` at `scale` of the image size is done (--budget: plan again when due)."""
        ...

    def finished(self, step: int, wall_seconds: float) -> bool:
        ...

    def end_at(self, step: int) -> None:
        """The run ends at `step` (--budget: what the last plan said, or fewer)."""
        ...
