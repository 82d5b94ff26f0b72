"""--steps N: the plan is made once, before the first step, and holds to the end (resume reads it back)."""

from __future__ import annotations

from dataclasses import replace


from ..config import TrainConfig
from ..data import Scene
from ..strategy import Strategy
from .run_plan import Plan
from .processes import for_processes
from .planner import RunState, RunStep
from .schedule import fitted_to_steps, planned_growth_rate


def initial_plan(config: TrainConfig, world_size: int = 1) -> Plan:
    """The plan a new run starts with, for `world_size` processes: with --steps the schedules fitted to them
    (unless --no-scale-schedule); with --budget the options as they are, until the planner's first plan."""
    plan = Plan.literal(config)
    if config.budget is None and config.scale_schedule:
        plan = fitted_to_steps(plan)
    return for_processes(plan, world_size)


def with_growth(plan: Plan, config: TrainConfig, gaussians: int, strategy: Strategy) -> Plan:
    """MCMC grows fast enough to reach --cap-max (or the automatic cap's ceiling, the `strategy`'s) from
    `gaussians` by growth_share of the run (at least at the paper's rate); the automatic cap stops it earlier where
    the scene asks for no more."""
    if config.strategy != "mcmc" or (config.cap_max is None and not config.mcmc.auto_cap):
        return plan
    rate = planned_growth_rate(plan, config.mcmc.growth_share, gaussians, strategy.ceiling)
    return replace(plan, schedule=replace(plan.schedule, grow_rate=rate))


class FixedSteps:
    """The planner of a --steps run: its plan never changes (the budget planner's counterpart, budget.py)."""

    budget_seconds = None

    def __init__(self, plan: Plan):
        self.plan = plan

    def begin(self, state: RunState, scene: Scene, step: RunStep) -> None:
        """Nothing to measure before the first step."""

    def after_step(self, seconds: float, gaussians: int, scale: float, *, step: int, wall_seconds: float,
                   gaussians_now: int) -> None:
        """Nothing to plan again."""

    def finished(self, step: int, wall_seconds: float) -> bool:
        return step >= self.plan.steps

    def end_at(self, step: int) -> None:
        """The run ends at its planned step."""
