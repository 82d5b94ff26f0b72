"""What a run decides, beside what the user asked: its plan (run_plan.py) and the planners that make it.

- run_plan.py: the Plan (steps, fitted schedules, cap and growth rate, resolution, processes, --budget's record);
- schedule.py: the paper's schedules fitted to a run's length, and the growth rate that reaches the cap in time;
- processes.py: the plan for N processes (a view each per step);
- fixed.py: --steps, one plan made before the first step; budget.py: --budget, planned again as the run goes, from
  step times measured on this machine (calibration.py: the first ones, before the clock starts);
- strategy_choice.py: the strategy a run asks for, on its plan's schedule;
- config_file.py: config.json, the configuration with its plan, written and read back;
- planner.py: what the loop asks of a planner (Planner), and what a planner sees of the run.

`planner_for` gives a run its planner; the trainer asks either kind the same things (the plan, whether the run is
done, and after each step what it took).
"""

from __future__ import annotations

from ..config import TrainConfig
from ..data import Scene
from .budget import BudgetPlanner, budget_planner
from .config_file import load_run_config, options_with_plan, read_record, run_record, save_run_config, settings_of
from .fixed import FixedSteps, initial_plan, with_growth
from .run_plan import REPLANNED_KEYS, SCHEDULE_KEYS, Plan
from .processes import for_processes
from .planner import Planner, RunState
from .strategy_choice import make_strategy

__all__ = ["BudgetPlanner", "FixedSteps", "Plan", "Planner", "REPLANNED_KEYS", "SCHEDULE_KEYS", "for_processes",
           "initial_plan", "load_run_config", "make_strategy", "options_with_plan", "planner_for", "read_record",
           "run_record", "save_run_config", "settings_of"]


def planner_for(config: TrainConfig, plan: Plan, scene: Scene, state: RunState, resumed: bool) -> Planner:
    """The planner of a run that starts (or resumes) with `plan` and `state`. A new --steps run with --cap-max gets
    the growth rate that reaches its cap in time."""
    if config.budget is not None:
        return budget_planner(config, plan, scene)
    return FixedSteps(plan if resumed else with_growth(plan, config, state.model.num_gaussians, state.strategy))
