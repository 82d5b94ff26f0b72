"""config.json: the configuration a run trains with and its plan, written as the run starts (and as --budget plans
again) and read back by --resume and by every command on a trained run.

The file keeps the layout it has always had: the options with the plan's values in their places (the steps and the
schedules fitted to them, the caps and the growth rate, the learning rates scaled for the processes: what the run
trains with, and what the file's readers, the report and the benchmarks, look for there), then `world_size` and
`budget_plan`. Read back, those values are the plan's (Plan.literal). A file written before the plan had a type of
its own also holds `schedule_fitted` (whether its schedules were fitted: they always are now), which is left aside.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..config import TrainConfig, from_jsonable, to_jsonable
from ..config_types import fits
from ..errors import MCSplatError
from ..io.atomic import atomic_write_text
from .plan import Plan

PLAN_ENTRIES = ("world_size", "budget_plan")  # the plan's own keys, beside the options
RETIRED_ENTRIES = ("schedule_fitted",)  # older files' keys that say nothing any more


def run_record(config: TrainConfig, plan: Plan) -> dict[str, Any]:
    """config.json's content (and the checkpoint's copy of it)."""
    record = to_jsonable(config)
    for key, value in plan.entries().items():
        group, _, name = key.rpartition(".")
        (record[group] if group else record)[name] = value
    record["optim"] = to_jsonable(plan.optim)
    return {**record, "world_size": plan.world_size, "budget_plan": plan.budget}


def read_record(data: Any) -> tuple[TrainConfig, Plan]:
    """The configuration and the plan of a config.json's content (a value of the wrong type, or an unknown key, is
    a one-line error: the file was edited by hand, or written by another version)."""
    if not isinstance(data, dict):
        from_jsonable(data)  # its one-line error
    config = from_jsonable({key: value for key, value in data.items()
                            if key not in PLAN_ENTRIES + RETIRED_ENTRIES})
    world_size = data.get("world_size", 1)
    if not fits(world_size, int):
        raise MCSplatError(f"config.json: world_size is {json.dumps(world_size)}, not a whole number; put back the "
                           f"value mcsplat wrote there")
    return config, Plan.literal(config, world_size, data.get("budget_plan"))


def save_run_config(path: Path, config: TrainConfig, plan: Plan) -> None:
    atomic_write_text(path, json.dumps(run_record(config, plan), indent=2) + "\n")


def load_run_config(path: Path) -> tuple[TrainConfig, Plan]:
    """The configuration and the plan saved in a config.json by save_run_config (or an older version)."""
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise MCSplatError(f"{path}: not valid JSON ({error})") from None
    return read_record(data)
