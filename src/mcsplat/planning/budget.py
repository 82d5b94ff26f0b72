"""--budget: train for a wall-clock time instead of a number of steps, and hand back the best result that time allows.

BudgetPlanner makes the run's plan (run_plan.py) and makes it again as the run goes; fixed.py is its counterpart for
--steps. The trainer asks either of them the same things: the plan, whether the run is done, and after each step
what it took.

The run keeps the shape of a step-scheduled run (schedule.py): coarse to fine up to `resolution_full_at` of the
steps, growth to the cap by `growth_share`, the paper's refinement window and learning-rate decay, all fitted to the
number of steps. What the budget decides is that number and the cap, from the time a step takes on this machine:

- A step's time is modelled as  t = a + b s^2 + c n + d n s^2  (s the share of the image size trained at, n the
  Gaussians in units of 100,000; non-negative coefficients), fitted to the steps measured so far, recent ones
  weighing more, and to a few timed steps at full size before the clock starts (`calibrate`).
- The cap balances the two costs of a step: where a full-size step spends twice as long on its Gaussians (c + d per
  Gaussian) as on its pixels (a + b), times sqrt(budget / 10 minutes), so that more time buys both more steps and
  more Gaussians (if the error falls as 1/steps + 1/Gaussians, the best count grows with the square root of the
  time). Twice, because on the demo scene at 95 s it scored above both once and three times (docs/quality.md, "The
  demo scene"). The automatic cap's ceiling of 3 Gaussians per pixel and --cap-max bound it, and it stays small
  enough to leave at least 1,000 steps. Where the scene asks for fewer (the automatic cap, on unless --cap-max gives
  a number, stops growth where the views stop asking for more), the plans that follow give the time saved to steps.
  A rule from the steps the time should give (8,000 in 10 minutes) instead of this ratio was tried and measured
  worse on the bird and the cup (docs/quality.md, 2026-11-28).
- How long the coarse phase lasts follows the same costs (unless --resolution-full-at is given): a step at a
  quarter of the size saves most of the share of a full-size step its pixels take (b + d n over the whole, at the
  planned cap), so the larger that share, the later full size comes: at 40% of the steps where pixels take 40% or
  less of a step, at the end where they take 80% or more, in proportion between. On the shared captures the best
  length followed that share: the captures whose pixels take most of a step gained most from a late full size, those
  in between peaked in the middle, and the demo scene, whose pixels take least, lost by it; chosen this way, the
  cup's 10 minutes scored above a fixed 0.4 (docs/quality.md, "Budget runs against the code before them" and "On a
  faster machine, with the coarse phase's length chosen (2026-11-26)"). It is chosen again at every plan until full
  size is reached, then kept.
- Each new plan's resolution rises from the size the run trains at when it is made: the geometric curve is bent to
  pass through it (`continuing_resolution`), so a plan that moves full size later, or asks more steps, never takes
  the size back down, and one that moves it earlier never jumps it up (unless full size is due at once). Without
  this, the size went up and down with the noisy choice: in fern's and DTU's 10 minutes it fell from nearly full
  size to little more than half at one plan and rose again at the next (docs/measurements-log.md, "The CPU loss's
  blurs in registers; --budget's size never steps back, 2026-11-27").
- The steps are those whose predicted times, with the count growing to the cap and the resolution rising as
  planned, fill the time left. The plan is made again every 2% of the budget (more often near its end) as the
  measured times come in, and the schedules are fitted again to the new number of steps. The SH schedule is kept
  once the degree has first risen, so the degree never steps back.
- The run stops at the planned step or when the budget is spent, whichever comes first. A run that reaches its
  planned step with more than END_SLACK of the budget left (its steps ran faster than measured: a machine whose
  other work stopped) plans again, so that it ends on time rather than early. The budget counts the
  training loop's wall-clock time (steps, periodic evaluations and checkpoints; pauses not counted); set-up (loading,
  initialisation, compiling, the calibration) and the final evaluation and export come on top.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import nnls

from ..config import TrainConfig, budget_seconds
from ..data import Scene
from ..errors import MCSplatError
from ..strategy.auto_cap import pixel_ceiling
from ..strategy.mcmc import MCMCSchedule, prune_to_cap
from .calibration import timed_steps
from .run_plan import Plan
from .planner import RunState, RunStep
from .schedule import PAPER_STEPS, growth_rate_reaching, refine_steps_between

BALANCE = 2.0                     # balanced_cap: Gaussians' time in a full-size step over the pixels'
MIN_STEPS, MAX_STEPS = 1000, 30_000  # the cap leaves at least MIN_STEPS; the search for steps stops at 10 x MAX
REPLAN_SHARE = 0.02               # a new plan every 2% of the budget
LATE_REPLAN_SHARE = 0.005         # ... every 0.5% in its last 10%
END_SLACK = 0.02                  # a run at its planned step with more than 2% of the budget left plans again
FIRST_PLAN_STEP = 10              # the first plan from measured steps
BUCKET = 10                       # steps summarised by their median time in the cost model
WARM_UP_STEPS = 3                 # the run's first steps (one-time costs) are left out of it
HALF_LIFE_STEPS = 300             # older measurements weigh half every 300 steps
PREDICTION_POINTS = 400           # the future steps are integrated on this many points
MIN_START_GAUSSIANS = 1000        # the first plan cuts a large initialisation to no fewer than this
PIXEL_SHARES, FULL_SIZE_AT = (0.4, 0.8), (0.4, 1.0)  # full size at 0.4 of the run at a pixel share of 0.4 ...


@dataclass
class StepCost:
    """Seconds per step as a + b s^2 + c n + d n s^2, fitted by non-negative least squares."""

    samples: list[tuple[float, float, float, float]] = field(default_factory=list)  # (seconds, n, s, weight 0/1)
    coefficients: np.ndarray = field(default_factory=lambda: np.zeros(4))

    @staticmethod
    def features(n: np.ndarray, s: np.ndarray) -> np.ndarray:
        n, s2 = np.asarray(n, dtype=float) / 1e5, np.asarray(s, dtype=float) ** 2
        return np.stack([np.ones_like(n), s2, n, n * s2], axis=-1)

    def add(self, seconds: float, gaussians: int, scale: float, calibration: bool = False) -> None:
        self.samples.append((seconds, float(gaussians), float(scale), 0.0 if calibration else 1.0))

    def fit(self) -> None:
        rows = np.array(self.samples, dtype=float)
        steps = rows[rows[:, 3] > 0][WARM_UP_STEPS:]
        groups = [steps[i:i + BUCKET] for i in range(0, len(steps), BUCKET)]
        summary = [(np.median(g[:, 0]), g[:, 1].mean(), g[:, 2].mean(), len(groups) - 1 - i)
                   for i, g in enumerate(groups)]
        summary += [(t, n, s, 0.0) for t, n, s, w in rows if w == 0]  # the calibration steps, full weight
        table = np.array(summary, dtype=float)
        weights = np.sqrt(0.5 ** (table[:, 3] * BUCKET / HALF_LIFE_STEPS))
        design = self.features(table[:, 1], table[:, 2]) * weights[:, None]
        self.coefficients, _ = nnls(design, table[:, 0] * weights)

    def predict(self, gaussians: np.ndarray, scale: np.ndarray) -> np.ndarray:
        return self.features(gaussians, scale) @ self.coefficients


def continuing_resolution(plan: Plan, step: int, scale: float) -> Plan:
    """`plan` with its coarse-to-fine curve passing through `scale` at `step` (the size the run trains at there):
    resolution_start becomes the start of the geometric rise through that point to full size at the plan's
    resolution_full_at. Where full size is due at or before `step`, the plan is kept (full size from there on)."""
    end = plan.resolution_full_at * plan.steps
    if scale >= 1.0 or step >= end:
        return plan
    return replace(plan, resolution_start=scale ** (end / (end - step)))


@dataclass
class Choice:
    """What each plan chooses; the schedules follow from its steps."""

    steps: int
    cap: int
    grow_rate: float


def budget_planner(config: TrainConfig, plan: Plan, scene: Scene) -> BudgetPlanner:
    """The planner of a --budget run starting (or resuming) with `plan`, bounded by --cap-max and the automatic cap's
    3 Gaussians per pixel."""
    if plan.world_size > 1:
        raise MCSplatError("--budget does not work with several training processes yet (each would plan its own "
                           "steps); give --steps instead")
    # The ceiling the run started with is the record's: a config.json of the older layout holds the last plan's cap
    # in --mcmc.cap-max's place (a run stopped at a small planned cap resumed capped there and scored far lower:
    # docs/measurements-log.md, "No cap collapses MCMC; the count from the scene without --cap-max, 2026-11-28").
    ceiling = (plan.budget or {}).get("ceiling")
    if ceiling is None:
        cap = config.max_gaussians or config.mcmc.cap_max  # ADC without a budget: MCMC's ceiling
        ceiling = pixel_ceiling(cap, scene.train_image_pixels, config.mcmc.gaussians_per_pixel)
    return BudgetPlanner(config, int(ceiling), plan)


class BudgetPlanner:
    """Plans and re-plans a --budget run (the module docstring says how). `config` is what the user asked; `plan`
    the plan the run starts with (a resumed run's, read back: its record keeps the base values and the history)."""

    def __init__(self, config: TrainConfig, ceiling: int, plan: Plan | None = None):
        self.config = config
        self.plan = plan or Plan.literal(config)
        self.budget_seconds = budget_seconds(config.budget)
        self.ceiling = ceiling  # the most Gaussians allowed whatever the time: --cap-max and 3 per pixel
        record = self.plan.budget or {}
        # The paper's schedule values the plan fits to each new number of steps (kept across a resume).
        # A plan saved before a key was added lacks it: the plan read back gives its value.
        self.base = {**self.plan.schedule_entries(), **(record.get("base") or {})}
        self.history: list[dict] = list(record.get("history", []))
        self.cost = StepCost()
        self.last_plan_at = -math.inf
        self.strategy = None  # the run's, from begin()
        self.sh_fixed = bool(record.get("sh_fixed", False))
        # The coarse phase's length is chosen from the costs unless given (kept across a resume by the record).
        self.full_size_chosen = bool(record.get("full_size_chosen", config.resolution_full_at is None))
        self.scale_now = self.plan.resolution_start  # the size the run trains at when a plan is made
        # The size of the run's first step (resolution_start moves with each plan: continuing_resolution).
        self.first_size = float(record.get("resolution_first", self.plan.resolution_start))

    # --------------------------------------------------------------------------------------------- the run
    def begin(self, state: RunState, scene: Scene, step: RunStep) -> None:
        """Before the clock starts: time a few steps, make the first plan, and cut an initialisation larger than
        it affords."""
        self.strategy = state.strategy  # whether the scene has stopped asking for more (its automatic cap)
        for seconds, gaussians, scale in timed_steps(self.config, self.plan, state.model, scene, step,
                                                     start=self.plan.resolution_at(state.step)):
            self.calibrate(seconds, gaussians, scale)
        self.start(state.step, state.wall_seconds, state.model.num_gaussians)
        if self.config.strategy == "mcmc" and state.step == 0:
            prune_to_cap(state.model, state.optimizers, self.plan.schedule.cap_max)

    def after_step(self, seconds: float, gaussians: int, scale: float, *, step: int, wall_seconds: float,
                   gaussians_now: int) -> None:
        """A step of `seconds` with `gaussians` at `scale` of the image size is done: measure it, plan again when
        due; when the time is up, this step is the last one."""
        self.observe(seconds, gaussians, scale)
        if self.due(step, wall_seconds):
            self.replan(step, wall_seconds, gaussians_now)
        if self.finished(step, wall_seconds):
            self.end_at(step)

    def end_at(self, step: int) -> None:
        """The run ends at `step`: what the last plan said, or fewer."""
        self._publish(replace(self.plan, steps=step))

    # ------------------------------------------------------------------------------------------- measurements
    def calibrate(self, seconds: float, gaussians: int, scale: float) -> None:
        """A timed step before the clock starts (e.g. at full size, where the run begins at a quarter)."""
        self.cost.add(seconds, gaussians, scale, calibration=True)

    def observe(self, seconds: float, gaussians: int, scale: float) -> None:
        self.cost.add(seconds, gaussians, scale)

    # --------------------------------------------------------------------------------------------- planning
    def start(self, step: int, wall_seconds: float, gaussians: int) -> None:
        """The plan the run starts (or resumes) with: from the calibration's costs when there are any, else
        MIN_STEPS at the current count until the first plan from measured steps."""
        self.scale_now = self.plan.resolution_at(step)
        if self.cost.samples:
            self.replan(step, wall_seconds, gaussians)
            self.last_plan_at = -math.inf  # the first plan from measured steps still comes at FIRST_PLAN_STEP
        else:
            self._apply(Choice(max(step + 1, MIN_STEPS), min(self.ceiling, max(gaussians, 1)),
                               self._base_rate()), step)

    def due(self, step: int, wall_seconds: float) -> bool:
        if step < FIRST_PLAN_STEP:
            return False
        if step >= self.plan.steps:  # ahead of the plan: plan again unless the time is (nearly) up
            return wall_seconds < (1.0 - END_SLACK) * self.budget_seconds
        share = LATE_REPLAN_SHARE if wall_seconds > 0.9 * self.budget_seconds else REPLAN_SHARE
        return wall_seconds - self.last_plan_at >= max(share * self.budget_seconds, 1.0)

    def replan(self, step: int, wall_seconds: float, gaussians: int) -> None:
        """A new plan from the costs measured so far."""
        self.cost.fit()
        self.scale_now = self.plan.resolution_at(step)  # before anything moves: the new plan rises from here
        if self.full_size_chosen and step < self.plan.resolution_full_at * self.plan.steps:
            self.plan = replace(self.plan, resolution_full_at=self.full_size_at(self._balanced_from(gaussians)))
        self._apply(self._choose(step, wall_seconds, gaussians), step)
        self.last_plan_at = wall_seconds
        self.history.append({"at_seconds": round(wall_seconds, 1), "step": step, "steps": self.plan.steps,
                             "cap": self.plan.schedule.cap_max, "gaussians": gaussians,
                             "full_size_at": round(self.plan.resolution_full_at, 3), "size": round(self.scale_now, 3),
                             "step_ms": round(1000 * float(self.cost.predict(gaussians, 1.0)), 1)})
        self._publish(self.plan)

    def finished(self, step: int, wall_seconds: float) -> bool:
        return step >= self.plan.steps or wall_seconds >= self.budget_seconds

    def _record(self, plan: Plan) -> dict:
        """What config.json (plan.budget) and the report keep of the planning."""
        return {"budget_seconds": self.budget_seconds, "steps": plan.steps, "cap": plan.schedule.cap_max,
                "ceiling": self.ceiling,
                "resolution_start": plan.resolution_start, "resolution_first": self.first_size,
                "resolution_full_at": plan.resolution_full_at,
                "full_size_chosen": self.full_size_chosen, "growth_share": self.config.mcmc.growth_share,
                "cost_model_ms": [round(1000 * float(c), 4) for c in self.cost.coefficients], "base": dict(self.base),
                "sh_fixed": self.sh_fixed, "history": list(self.history)}

    def _publish(self, plan: Plan) -> None:
        """`plan` becomes the run's, with the record of the planning so far."""
        self.plan = replace(plan, budget=self._record(plan))

    def _choose(self, step: int, wall_seconds: float, gaussians: int) -> Choice:
        """The cap of `balanced_cap` (within the ceiling, and small enough to leave MIN_STEPS), and the steps that
        fill the time left with it.

        The cap never falls below the current count once the run is under way (pruning a trained model costs
        more than the steps it saves). Only the starting count can be cut (MCMC keeps the most opaque: a random
        initialisation of more points than the budget affords). Once growth is over (growth_share of the run, or
        the scene has stopped asking for more: the automatic cap, on unless --cap-max gives a number) the cap is
        the count reached, and the plans that follow give the time it saves to steps."""
        left = self.budget_seconds - wall_seconds
        current = max(gaussians, 1)
        top = max(self.ceiling, 1)
        growth_over = step >= self._growth_ends()
        if growth_over or getattr(self.strategy, "chosen_cap", None) is not None:
            return Choice(self._steps_for(step, left, current, current), current, self._base_rate())
        lowest = min(top, max(MIN_START_GAUSSIANS, current // 10) if step == 0 else current)
        cap = self._balanced_from(lowest)
        steps = self._steps_for(step, left, current, cap)
        while steps < MIN_STEPS and cap > lowest:
            cap = max(lowest, int(cap * 0.8))
            steps = self._steps_for(step, left, current, cap)
        return Choice(steps, cap, self._grow_rate(step, steps, current, cap))

    def balanced_cap(self) -> int:
        """The count at which a full-size step spends BALANCE times as long on its Gaussians as on its pixels,
        times sqrt(budget / 10 minutes): a longer budget buys more Gaussians as well as more steps."""
        a, b, c, d = self.cost.coefficients
        per_gaussian = (c + d) / 1e5
        if per_gaussian <= 0:
            return max(self.ceiling, 1)
        return int(BALANCE * (a + b) / per_gaussian * math.sqrt(self.budget_seconds / 600.0))

    def _balanced_from(self, lowest: int) -> int:
        """The balanced cap, at least `lowest` and at most the ceiling."""
        return min(max(self.ceiling, 1), max(lowest, self.balanced_cap()))

    def pixel_share(self, gaussians: int) -> float:
        """The share of a full-size step of `gaussians` that its pixels take (b + d n over the whole); 0 before
        anything is measured."""
        a, b, c, d = self.cost.coefficients
        n = gaussians / 1e5
        whole = a + b + (c + d) * n
        return float((b + d * n) / whole) if whole > 0 else 0.0

    def full_size_at(self, cap: int) -> float:
        """The share of the run by which it reaches full size, from the pixel share of a step at `cap`."""
        return float(np.interp(self.pixel_share(cap), PIXEL_SHARES, FULL_SIZE_AT))

    def _steps_for(self, step: int, left: float, gaussians: int, cap: int) -> int:
        """The number of steps (in all) whose predicted times fill `left` seconds from `step` on."""
        low, high = step + 1, step + 1
        while self._future_seconds(step, high, gaussians, cap) < left and high < 10 * MAX_STEPS:
            low, high = high, high * 2
        while high - low > max(1, low // 200):
            middle = (low + high) // 2
            if self._future_seconds(step, middle, gaussians, cap) < left:
                low = middle
            else:
                high = middle
        return low

    def _future_seconds(self, step: int, steps: int, gaussians: int, cap: int) -> float:
        """Predicted seconds of the steps from `step` to `steps` when the run lasts `steps` steps in all."""
        if steps <= step:
            return 0.0
        ks = np.unique(np.linspace(step, steps - 1, min(PREDICTION_POINTS, steps - step)).round())
        trial = continuing_resolution(self._fitted(steps), step, self.scale_now)
        end = trial.resolution_full_at * steps
        # The exponent clipped at 0 past full size: the discarded branch of np.where raised 0 (a start size that
        # underflowed) or a tiny start to negative powers, and numpy's warnings reached the user's console.
        scales = np.power(trial.resolution_start, np.clip(1.0 - ks / max(end, 1e-9), 0.0, 1.0))
        per_step = self.cost.predict(self._counts(trial, step, ks, gaussians, cap), scales)
        return float(np.trapezoid(per_step, ks) + per_step[-1]) if len(ks) > 1 else float(per_step[0])

    def _counts(self, trial: Plan, step: int, ks: np.ndarray, gaussians: int, cap: int) -> np.ndarray:
        """The Gaussians at steps `ks` as MCMC grows towards `cap` at the planned rate (ADC: the cap, at most)."""
        if self.config.strategy != "mcmc":
            return np.full(len(ks), float(cap))
        if cap <= gaussians:
            return np.full(len(ks), float(cap))
        m = trial.schedule
        rate = self._grow_rate(step, trial.steps, gaussians, cap)
        first = (max(step, m.refine_start) // m.refine_every + 1) * m.refine_every
        upto = np.minimum(ks + 1, m.refine_stop) - 1
        refines = np.where(upto >= first, (upto - first) // m.refine_every + 1, 0)
        # In logs, bounded at the cap: a large rate to a high power overflowed (numpy warned on the console).
        return np.exp(np.minimum(np.log(cap), math.log(gaussians) + refines * math.log(rate)))

    def _base_rate(self) -> float:
        """MCMC's growth rate before any is planned (ADC has none: 1)."""
        return self.base.get("mcmc.grow_rate", 1.0)

    def _growth_ends(self) -> float:
        """The step at which the run stops adding Gaussians: MCMC at growth_share of the run or where its refinement
        stops, ADC where its densification stops."""
        schedule = self.plan.schedule
        if isinstance(schedule, MCMCSchedule):
            return min(self.config.mcmc.growth_share * self.plan.steps, schedule.refine_stop)
        return schedule.densify_stop

    def _grow_rate(self, step: int, steps: int, gaussians: int, cap: int) -> float:
        m = self._fitted(steps).schedule
        if not isinstance(m, MCMCSchedule):
            return 1.0
        refines = refine_steps_between(max(step, m.refine_start),
                                       min(round(self.config.mcmc.growth_share * steps), m.refine_stop),
                                       m.refine_every)
        return growth_rate_reaching(gaussians, cap, refines, m.grow_rate)

    def _fitted(self, steps: int) -> Plan:
        """The plan's base schedules fitted to `steps` (the SH schedule kept once the degree has risen)."""
        fitted = replace(self.plan.with_schedule(self.base), steps=steps).scaled(steps, PAPER_STEPS)
        return replace(fitted, sh_increase_every=self.plan.sh_increase_every) if self.sh_fixed else fitted

    def _apply(self, choice: Choice, step: int) -> None:
        if not self.sh_fixed and step >= self.plan.sh_increase_every:
            self.sh_fixed = True  # the degree has risen once: keep its schedule so it never steps back
        fitted = continuing_resolution(self._fitted(choice.steps), step, self.scale_now)
        planned = {"cap_max": choice.cap}
        if isinstance(fitted.schedule, MCMCSchedule):
            planned["grow_rate"] = choice.grow_rate
        self._publish(replace(fitted, schedule=replace(fitted.schedule, **planned)))
