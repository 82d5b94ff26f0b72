"""config.json: what the user asked and the run's plan beside it, written as the run starts (and as --budget plans
again), read back by --resume and by every command on a trained run.

The file holds the options as the command line (or the Python API) gave them, then `plan`: what the run decided
(the steps and the schedules fitted to them, the cap and the growth rate, the coarse-to-fine resolution, the
learning rates scaled for the processes, `world_size`, and --budget's record of how it planned: Plan.record), and
`scene`: a fingerprint of the scene the run trains on (its kind, its views' counts, a digest of their names and image
sizes; run/scene.py's scene_fingerprint), by which --resume knows it wherever it is now.

Files written until 2026-11-28 have no `plan`: the plan's values stood in the options' places, with `world_size`
and `budget_plan` beside them (and, before the plan had a type, `schedule_fitted`, left aside). Read back, those
values are taken as the plan (Plan.literal), and as the options too, since what the user asked was not kept. That
older layout is also the form in which two sets of settings are compared (`options_with_plan`): a value there is the
one the run trains with.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..config import TrainConfig, flat_options, from_jsonable, to_jsonable
from ..typed_json import fits
from ..errors import MCSplatError
from ..io.atomic import atomic_write_text
from .run_plan import Plan

PLAN_ENTRY = "plan"  # the run's plan, beside the options
OLD_PLAN_ENTRIES = ("world_size", "budget_plan")  # the plan's own keys beside the options, in the older layout
SCENE_ENTRY = "scene"  # the fingerprint of the run's scene, beside the options
SCENE_FIELDS = {"kind": str, "train_views": int, "test_views": int, "views": str}
CAP_MAX_SETS = ("mcmc.cap_max", "adc.cap_max", "mcmc.auto_cap")  # the keys TrainConfig derives from cap_max
RETIRED_ENTRIES = ("schedule_fitted",)  # older files' keys that say nothing any more


def run_record(config: TrainConfig, plan: Plan, scene: dict[str, Any] | None = None) -> dict[str, Any]:
    """config.json's content (and, without the `scene` fingerprint, the checkpoint's copy of it): the options as
    asked, the plan beside them."""
    record = {**to_jsonable(config), PLAN_ENTRY: plan.record()}
    return record if scene is None else {**record, SCENE_ENTRY: scene}


def options_with_plan(config: TrainConfig, plan: Plan) -> dict[str, Any]:
    """The options with the plan's values in their places (steps, schedules, caps, learning rates), `world_size` and
    `budget_plan` beside them: the older layout of config.json, and the form in which the settings of a checkpoint,
    a config.json and a command line are compared, each value being what the run trains with."""
    record = to_jsonable(config)
    for key, value in plan.entries().items():
        group, _, name = key.rpartition(".")
        (record[group] if group else record)[name] = value
    record["optim"] = to_jsonable(plan.optim)
    return {**record, "world_size": plan.world_size, "budget_plan": plan.budget}


def settings_of(record: dict[str, Any]) -> dict[str, Any]:
    """A config.json's content or a checkpoint's copy of it, of either layout, as options_with_plan gives it."""
    if PLAN_ENTRY not in record:
        return {key: value for key, value in record.items() if key not in RETIRED_ENTRIES + (SCENE_ENTRY,)}
    return options_with_plan(*read_record(record))


def read_record(data: Any) -> tuple[TrainConfig, Plan]:
    """The configuration and the plan of a config.json's content (a value of the wrong type, or an unknown key, is
    a one-line error: the file was edited by hand, or written by another version)."""
    if not isinstance(data, dict):
        from_jsonable(data)  # its one-line error
    if PLAN_ENTRY in data:
        config = from_jsonable({key: value for key, value in data.items() if key not in (PLAN_ENTRY, SCENE_ENTRY)})
        refuse_what_cap_max_overrides(data, config)
        return config, Plan.from_record(data[PLAN_ENTRY], config.strategy)
    config = from_jsonable({key: value for key, value in data.items()
                            if key not in OLD_PLAN_ENTRIES + RETIRED_ENTRIES + (SCENE_ENTRY,)})
    refuse_what_cap_max_overrides(data, config)
    world_size = data.get("world_size", 1)
    if not fits(world_size, int):
        raise MCSplatError(f"config.json: world_size is {json.dumps(world_size)}, not a whole number; put back the "
                           f"value mcsplat wrote there")
    return config, Plan.literal(config, world_size, data.get("budget_plan"))


def refuse_what_cap_max_overrides(data: dict[str, Any], config: TrainConfig) -> None:
    """`cap_max` sets `mcmc.cap_max`, `adc.cap_max` and `mcmc.auto_cap` as the configuration is made (`config`, from
    the file's content `data`): a file holding other values there (edited by hand) would have them ignored without a
    word. A --budget run's file of the older layout holds its plan's cap in the caps' places, which is at most the
    configuration's."""
    written, made = flat_options(data), flat_options(to_jsonable(config))
    for key in CAP_MAX_SETS:
        value = written.get(key, made[key])  # a key left out: an older file's default, which cap_max sets too
        if value == made[key]:
            continue
        if key.endswith("cap_max") and config.budget is not None and fits(value, int) and value <= made[key]:
            continue
        raise MCSplatError(f"config.json: {key} is {json.dumps(value)}, but cap_max {json.dumps(data.get('cap_max'))} "
                           f"makes it {json.dumps(made[key])}, so that value would be ignored; make them agree (with "
                           f"cap_max null, mcmc.cap_max is the ceiling of the automatic cap)")


def read_scene_entry(data: Any) -> dict[str, Any] | None:
    """The fingerprint of the run's scene in a config.json's content; None in a file written before it."""
    scene = data.get(SCENE_ENTRY) if isinstance(data, dict) else None
    if scene is None:
        return None
    if not (isinstance(scene, dict) and scene.keys() == SCENE_FIELDS.keys()
            and all(fits(scene[key], kind) for key, kind in SCENE_FIELDS.items())):
        raise MCSplatError(f"config.json: {SCENE_ENTRY} is {json.dumps(scene)}, not the fingerprint mcsplat wrote "
                           f"there; put it back, or remove the entry to resume without checking the scene")
    return scene


def save_run_config(path: Path, config: TrainConfig, plan: Plan, scene: dict[str, Any] | None = None) -> None:
    atomic_write_text(path, json.dumps(run_record(config, plan, scene), indent=2) + "\n")


def save_scene_entry(path: Path, data: Path, scene: dict[str, Any]) -> None:
    """config.json naming the scene at `data`, with its fingerprint `scene` (a resumed run's scene, moved, or in a
    file written before the fingerprint); the rest of the file as it is."""
    record = json.loads(path.read_text())
    updated = {**record, "data": str(data), SCENE_ENTRY: scene}
    if updated != record:
        atomic_write_text(path, json.dumps(updated, indent=2) + "\n")


def load_run_config(path: Path) -> tuple[TrainConfig, Plan]:
    """The configuration and the plan saved in a config.json by save_run_config (or an older version)."""
    return read_record(_load_json(path))


def load_run_record(path: Path) -> tuple[TrainConfig, Plan, dict[str, Any] | None]:
    """The configuration, the plan and the scene's fingerprint of a config.json, from one reading of it."""
    data = _load_json(path)
    return (*read_record(data), read_scene_entry(data))


def load_scene_entry(path: Path) -> dict[str, Any] | None:
    """The fingerprint of the run's scene saved in a config.json; None in a file written before it."""
    return read_scene_entry(_load_json(path))


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise MCSplatError(f"{path}: not valid JSON ({error})") from None
