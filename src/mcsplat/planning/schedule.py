"""How the paper's 30,000-step schedule is fitted to a run's length, and the growth rate that reaches the cap in time.

The options give the paper's values for a 30,000-step run (refinement from 500 to 25,000 every 100 steps, ADC's
densification and opacity resets, the SH degree every 1,000 steps). A run of --steps N multiplies every one of them
by N / 30,000, as gsplat's steps_scaler does, so a short run refines, grows and raises its SH degree at the same
points of the run as the paper's (--no-scale-schedule takes the options as steps of this run). The position learning
rate's decay always spans the run's own steps.
"""

from __future__ import annotations

from .run_plan import Plan

PAPER_STEPS = 30_000


def fitted_to_steps(plan: Plan) -> Plan:
    """`plan` with the paper's schedules (its values) fitted to its steps."""
    return plan.scaled(plan.steps, PAPER_STEPS)


def planned_growth_rate(plan: Plan, growth_share: float, num_initial: int, cap: int) -> float:
    """The growth factor per refine step that takes `num_initial` Gaussians to `cap` by `growth_share` of the run,
    or the plan's rate (the paper's 1.05) where that is already fast enough."""
    m = plan.schedule  # MCMC's
    refines = refine_steps_between(m.refine_start, min(round(growth_share * plan.steps), m.refine_stop),
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
