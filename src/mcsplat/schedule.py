"""The run's step schedules: how the paper's 30,000-step schedule is fitted to the run's length, the SH degree and the
training resolution at a step, and the growth rate that reaches the cap in time.

The options give the paper's values for a 30,000-step run (refinement from 500 to 25,000 every 100 steps, ADC's
densification and opacity resets, the SH degree every 1,000 steps). A run of --steps N multiplies every one of them
by N / 30,000, as gsplat's steps_scaler does, so a short run refines, grows and raises its SH degree at the same
points of the run as the paper's (--no-scale-schedule takes the options as steps of this run). The position learning
rate's decay always spans the run's own steps.
"""

from __future__ import annotations

import copy

from .config import TrainConfig

PAPER_STEPS = 30_000


def scale_step_schedules(config: TrainConfig, numerator: int, denominator: int) -> None:
    """Multiply every step schedule of `config` by numerator / denominator, in place (intervals stay at least one
    step). The position learning rate is not among them: its decay follows --steps."""

    def every(steps: int) -> int:
        return max(1, round(steps * numerator / denominator))

    def at(step: int) -> int:
        return round(step * numerator / denominator)

    config.sh_increase_every = every(config.sh_increase_every)
    m, a = config.mcmc, config.adc
    m.refine_start, m.refine_stop, m.refine_every = at(m.refine_start), at(m.refine_stop), every(m.refine_every)
    a.densify_start, a.densify_stop = at(a.densify_start), at(a.densify_stop)
    a.densify_every, a.reset_every = every(a.densify_every), every(a.reset_every)
    m.param_noise_decay = m.param_noise_decay ** (denominator / numerator)  # the same decay over the run


def fitted_to_steps(config: TrainConfig) -> TrainConfig:
    """A copy of a new run's configuration with its step schedules fitted to its --steps (itself when
    --no-scale-schedule, or when it is already fitted: a resumed run's saved configuration)."""
    if not config.scale_schedule or config.schedule_fitted:
        return config
    fitted = copy.deepcopy(config)
    scale_step_schedules(fitted, config.steps, PAPER_STEPS)
    fitted.schedule_fitted = True
    return fitted


def sh_degree_at(config: TrainConfig, step: int) -> int:
    """The SH degree a step renders with (0-based step): one more every `sh_increase_every` steps, up to the
    model's degree, as 3DGS raises it at iterations 1000, 2000, 3000."""
    return min(step // config.sh_increase_every, config.model.sh_degree)


def final_sh_degree(config: TrainConfig, steps_done: int) -> int:
    """The SH degree of the last step taken, after `steps_done` steps: what a finished model is shown with."""
    return sh_degree_at(config, max(steps_done - 1, 0))


def resolution_at(config: TrainConfig, step: int) -> float:
    """The share of the full image size a step trains at: `resolution_start` at the first step, rising
    geometrically to 1 at `resolution_full_at` of the run (coarse to fine), 1 from there on."""
    start = config.resolution_start
    end = config.resolution_full_at * config.steps
    if start >= 1.0 or step >= end:
        return 1.0
    return start ** (1.0 - step / end)


def planned_growth_rate(config: TrainConfig, num_initial: int, cap: int) -> float:
    """The growth factor per refine step that takes `num_initial` Gaussians to `cap` by `growth_share` of the run,
    or the configured rate (the paper's 1.05) where that is already fast enough."""
    m = config.mcmc
    refines = refine_steps_between(m.refine_start, min(round(m.growth_share * config.steps), m.refine_stop),
                                   m.refine_every)
    return growth_rate_reaching(num_initial, cap, refines, m.grow_rate)


def growth_rate_reaching(count: int, cap: int, refines: int, least: float) -> float:
    """The smallest factor >= `least` with which MCMC's growth (N <- min(cap, int(factor N)) at each refine step)
    takes `count` Gaussians to `cap` in `refines` refine steps."""
    def reached(factor: float) -> bool:
        n = count
        for _ in range(refines):
            n = min(cap, int(factor * n))
        return n >= cap

    if count <= 0 or cap <= count or refines < 1 or reached(least):
        return least
    low, high = least, max(least, (cap / count) ** (1.0 / refines)) * 1.5
    while not reached(high):
        high *= 1.5
    for _ in range(40):
        middle = 0.5 * (low + high)
        low, high = (low, middle) if reached(middle) else (middle, high)
    return high


def refine_steps_between(start: int, stop: int, every: int) -> int:
    """How many steps k with start < k < stop are multiples of `every` (MCMC's and ADC's refine steps)."""
    first = (start // every + 1) * every
    return max(0, (stop - 1 - first) // every + 1) if stop - 1 >= first else 0
