"""A run's plan: what the run decides, beside what the user asked (the configuration, config.py).

The plan holds the run's number of steps, every step schedule fitted to it (refinement, ADC's densification and
opacity resets, the SH increase, the parameter noise's decay), the cap and the growth rate, the coarse-to-fine
resolution, the number of processes with the learning rates scaled for them, and --budget's record of how it planned.
A planner makes it (fixed.py for --steps, budget.py for --budget); the step reads it, the strategy follows its part
of it, and config.json and the checkpoint keep it beside the options (config_file.py), so that --resume continues it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Mapping

from ..config import RESOLUTION_FULL_AT, TrainConfig, to_jsonable
from ..typed_json import checked_dataclass
from ..errors import MCSplatError
from ..optim import OptimConfig
from ..strategy import ADCSchedule, MCMCSchedule

# The strategies' schedules, by the group config.json keeps each in (a run's plan holds its strategy's; files written
# before 2026-11-29 hold one of each, the other strategy's left aside when read back).
SCHEDULES = {"mcmc": MCMCSchedule, "adc": ADCSchedule}
# The schedule values a plan fits to its steps, named as config.json names them (--budget keeps the values it
# started from under these keys, its "base"): the SH increase, and a strategy's scheduled fields (their metadata).
SCHEDULE_KEYS = ("sh_increase_every",) + tuple(f"{group}.{f.name}" for group, cls in SCHEDULES.items()
                                               for f in fields(cls) if "schedule" in f.metadata)
# What a --budget run plans again as it goes: config.json may hold another plan than the one its checkpoint took.
REPLANNED_KEYS = frozenset(("steps", "resolution_start", "resolution_full_at", *SCHEDULE_KEYS)
                           + tuple(f"{group}.cap_max" for group in SCHEDULES))


@dataclass(frozen=True)
class Plan:
    steps: int
    sh_increase_every: int  # the SH degree rises by one every this many steps ...
    sh_degree: int  # ... up to the model's
    # Coarse to fine: the share of the image size of the first step, rising geometrically to full size at
    # resolution_full_at of the steps (--budget bends the curve at each new plan to go on from the size the run
    # trains at then, through a start of its own: budget.continuing_resolution).
    resolution_start: float
    resolution_full_at: float
    schedule: MCMCSchedule | ADCSchedule  # the run's strategy's: config.json keeps it under the strategy's group
    optim: OptimConfig  # the learning rates, scaled for the processes
    world_size: int = 1  # processes training together, a view each per step
    budget: dict[str, Any] | None = None  # --budget: how it planned (config.json's plan.budget)

    @classmethod
    def literal(cls, config: TrainConfig, world_size: int = 1, budget: dict[str, Any] | None = None) -> Plan:
        """The configuration's values taken as they are: a run's saved configuration (its values are the plan's),
        or the options before anything is fitted."""
        full_at = RESOLUTION_FULL_AT if config.resolution_full_at is None else config.resolution_full_at
        return cls(steps=config.steps, sh_increase_every=config.sh_increase_every, sh_degree=config.model.sh_degree,
                   resolution_start=config.resolution_start, resolution_full_at=full_at,
                   schedule=SCHEDULES[config.strategy].of(getattr(config, config.strategy)), optim=config.optim,
                   world_size=world_size, budget=budget)

    @property
    def strategy(self) -> str:
        """The group of the strategy whose schedule the plan holds ("mcmc", "adc")."""
        return next(group for group, kind in SCHEDULES.items() if isinstance(self.schedule, kind))

    def record(self) -> dict[str, Any]:
        """The plan as config.json keeps it, beside the options (`plan`): the schedule under its strategy's group."""
        return {(self.strategy if key == "schedule" else key): value for key, value in to_jsonable(self).items()}

    @classmethod
    def from_record(cls, record: Any, strategy: str, source: str = "config.json") -> Plan:
        """The plan that `record()` wrote for a run of `strategy` (a value of another type, a key missing or unknown:
        one line naming it). Another strategy's schedule beside it (files written before 2026-11-29) is left aside; a
        plan of another strategy alone is read as it is (config.json's strategy edited by hand: the resume's
        comparison names it)."""
        if isinstance(record, dict):
            held = [group for group in SCHEDULES if group in record]
            strategy = strategy if strategy in held or len(held) != 1 else held[0]
        if isinstance(record, dict) and strategy in record:
            schedule = checked_dataclass(SCHEDULES[strategy], record[strategy], source, f"plan.{strategy}.",
                                         complete=True)
            record = {**{k: v for k, v in record.items() if k not in SCHEDULES}, "schedule": to_jsonable(schedule)}
        elif isinstance(record, dict):
            raise MCSplatError(f"{source}: plan lacks {strategy} (written by another mcsplat version?)")
        return checked_dataclass(cls, record, source, "plan.", complete=True,
                                 nested={"schedule": SCHEDULES[strategy], "optim": OptimConfig})

    def schedule_entries(self) -> dict[str, Any]:
        """The SCHEDULE_KEYS values of the plan (its strategy's)."""
        return {"sh_increase_every": self.sh_increase_every,
                **{f"{self.strategy}.{name}": value for name, value in self.schedule.entries().items()}}

    def with_schedule(self, entries: Mapping[str, Any]) -> Plan:
        """The plan with the schedule values `entries` gives (its strategy's SCHEDULE_KEYS; others are ignored)."""
        schedule = self.schedule.with_entries({name: entries[f"{self.strategy}.{name}"]
                                               for name in self.schedule.entries()})
        return replace(self, sh_increase_every=entries["sh_increase_every"], schedule=schedule)

    def scaled(self, numerator: int, denominator: int) -> Plan:
        """The plan with every step schedule multiplied by numerator / denominator, as each field's kind says
        (strategy/base.py: intervals stay at least one step, decays keep their decay over the run). The steps are
        not among them, nor the position learning rate, whose decay follows the steps."""
        every = max(1, round(self.sh_increase_every * numerator / denominator))
        return replace(self, sh_increase_every=every, schedule=self.schedule.scaled(numerator, denominator))

    def entries(self) -> dict[str, Any]:
        """The plan's values under the options' keys ("mcmc.cap_max"): the places they take in the older layout of
        config.json, and in the settings compared on resume (config_file.options_with_plan)."""
        return {"steps": self.steps, **self.schedule_entries(), "resolution_start": self.resolution_start,
                "resolution_full_at": self.resolution_full_at, f"{self.strategy}.cap_max": self.schedule.cap_max}

    def sh_degree_at(self, step: int) -> int:
        """The SH degree a step renders with (0-based step): one more every `sh_increase_every` steps, up to the
        model's degree, as 3DGS raises it at iterations 1000, 2000, 3000."""
        return min(step // self.sh_increase_every, self.sh_degree)

    def final_sh_degree(self, steps_done: int) -> int:
        """The SH degree of the last step taken, after `steps_done` steps: what a finished model is shown with."""
        return self.sh_degree_at(max(steps_done - 1, 0))

    def resolution_at(self, step: int) -> float:
        """The share of the full image size a step trains at: `resolution_start` at the first step, rising
        geometrically to 1 at `resolution_full_at` of the run (coarse to fine), 1 from there on."""
        start = self.resolution_start
        end = self.resolution_full_at * self.steps
        if start >= 1.0 or step >= end:
            return 1.0
        return start ** (1.0 - step / end)
