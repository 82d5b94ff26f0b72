"""What the user asked and what the run decides are two values: the configuration, frozen once it is made, and the
plan (its steps, the schedules fitted to them, cap, growth, resolution, processes) that the step and the strategy
read, that config.json keeps, and that --resume reads back, from the files an older mcsplat wrote too."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
import tyro

from mcsplat.cli import COMMANDS
from mcsplat.config import ModelConfig, TrainConfig, to_jsonable
from mcsplat.errors import MCSplatError
from mcsplat.run.events import Subscriber
from mcsplat.io.checkpoint import load_checkpoint
from mcsplat.planning import (Plan, initial_plan, load_run_config, make_strategy, options_with_plan, read_record,
                              run_record)
from mcsplat.planning.schedule import PAPER_STEPS
from mcsplat.strategy import ADCSchedule, MCMCSchedule
from mcsplat.train import train

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


def parsed(*options: str) -> TrainConfig:
    """The configuration `mcsplat train DEMO <options>` parses to."""
    return tyro.extras.subcommand_cli_from_dict(COMMANDS, args=["train", str(DEMO), *options])


def test_the_configuration_cannot_be_changed_once_parsed():
    config = parsed("--steps", "60", "--mcmc.cap-max", "5000")
    for owner, name, value in ((config, "steps", 5), (config.mcmc, "cap_max", 6000), (config.model, "sh_degree", 1),
                               (config.optim, "means_lr", 1.0), (config.adc, "reset_every", 7)):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(owner, name, value)
    assert (config.steps, config.mcmc.cap_max) == (60, 5000), "the values it was made with"
    derived = dataclasses.replace(config, steps=90)
    assert (derived.steps, config.steps) == (90, 60), "replace derives another value; the first stays"


def test_the_flags_keep_their_names():
    config = parsed("--appearance", "affine", "--appearance-lr", "0.01", "--pose-opt", "--pose-opt-lr", "0.001",
                    "--eval-every", "3", "--mcmc.refine-start", "5", "--model.num-init-points", "100",
                    "--optim.means-lr", "0.0002", "--cap-max", "auto", "--no-scale-schedule")
    compensation, poses = config.compensation, config.poses  # each feature's options, in its own group
    assert (compensation.appearance, compensation.appearance_lr, poses.pose_opt, poses.pose_opt_lr) == (
        "affine", 0.01, True, 0.001)
    assert (config.eval_every, config.mcmc.refine_start, config.model.num_init_points) == (3, 5, 100)
    assert config.optim.means_lr == 0.0002 and config.mcmc.auto_cap and not config.scale_schedule


def test_each_feature_group_keeps_its_flags_and_config_json_its_keys():
    """A feature's options are a group of TrainConfig (features.py) whose flags keep no prefix, and config.json keeps
    them beside the others under the same names: a file written before the groups reads as it did. No option is
    named twice, nor a group like an option (the key would be read as the group)."""
    import typing

    from mcsplat.config import ViewerOptions, config_of, from_jsonable, option_value, with_options
    from mcsplat.typed_json import flat_groups
    from mcsplat.surface_terms import SurfaceOptions

    hints = typing.get_type_hints(TrainConfig)
    groups = flat_groups(TrainConfig)
    assert {"compensation", "poses", "surface_terms", "depth_terms", "training_masks", "depth_maps",
            "live_viewer"} <= set(groups)
    names = [f.name for group in groups for f in dataclasses.fields(hints[group])]
    names += [f.name for f in dataclasses.fields(TrainConfig)]
    assert len(names) == len(set(names)), "an option named twice"
    config = parsed("--surface", "--surface-from", "0.4", "--masks", "none", "--depths", "auto", "--port", "9000")
    assert (config.surface_terms.surface, config.surface_terms.surface_from, config.training_masks.masks,
            config.depth_maps.depths, config.live_viewer.port) == (True, 0.4, "none", "auto", 9000)
    saved = to_jsonable(config)
    assert not set(groups) & set(saved) and (saved["surface_from"], saved["masks"], saved["port"]) == (0.4, "none",
                                                                                                   9000)
    assert from_jsonable(saved) == config
    assert option_value(config, "surface_from") == 0.4 and option_value(config, "mcmc.cap_max") == config.mcmc.cap_max
    assert with_options(config, surface_from=0.5, steps=7) == from_jsonable({**saved, "surface_from": 0.5, "steps": 7})
    assert config_of(data=DEMO, surface=True, port=9) == TrainConfig(
        data=DEMO, surface_terms=SurfaceOptions(surface=True), live_viewer=ViewerOptions(port=9))
    with pytest.raises(MCSplatError, match="surface_from is \"soon\", not a number"):
        from_jsonable({**saved, "surface_from": "soon"})
    with pytest.raises(MCSplatError, match="unknown option 'surface_terms'"):  # not read, and dropped, in silence
        from_jsonable({**saved, "surface_terms": {"surface": False}})


def test_the_strategy_follows_the_plan_and_the_options_stay():
    """--steps 3000 fits refinement to every 10 steps from 50: the strategy refines there, though its options
    (the paper's, for 30,000 steps) say every 100 from 500; a new plan (--budget plans again) moves it."""
    config = TrainConfig(data=DEMO, steps=3000, cap_max=5000)
    plan = initial_plan(config)
    strategy = make_strategy(config, plan, 1.0, torch.Generator())
    assert (config.mcmc.refine_start, config.mcmc.refine_every) == (500, 100)
    assert strategy.is_refine_step(60) and not strategy.is_refine_step(65) and strategy.ceiling == 5000
    strategy.follow(dataclasses.replace(plan.schedule, refine_every=7, cap_max=4000))
    assert strategy.is_refine_step(63) and not strategy.is_refine_step(60) and strategy.ceiling == 4000
    adc = TrainConfig(data=DEMO, steps=3000, strategy="adc")
    densifying = make_strategy(adc, initial_plan(adc), 1.0, torch.Generator())
    assert densifying.is_densify_step(60) and densifying.is_reset_step(300) and adc.adc.reset_every == 3000


def test_config_json_keeps_what_was_asked_and_the_plan_beside_it():
    """The options as the user gave them, the plan beside them (with the processes and the --budget record). What
    is read back is the configuration asked and the plan."""
    config = TrainConfig(data=DEMO, steps=3000, cap_max=5000)
    plan = dataclasses.replace(initial_plan(config, 2), budget={"history": [{"step": 1}]})
    record = json.loads(json.dumps(run_record(config, plan)))
    assert (record["steps"], record["mcmc"]["refine_every"], record["sh_increase_every"]) == (3000, 100, 1000)
    assert record["optim"] == to_jsonable(config.optim), "the learning rates asked, not those scaled for 2 processes"
    planned = record["plan"]
    assert (planned["steps"], planned["mcmc"]["refine_every"], planned["sh_increase_every"]) == (1500, 5, 50)
    assert planned["world_size"] == 2 and planned["budget"] == {"history": [{"step": 1}]}
    assert "adc" not in planned, "the plan holds the schedule of the run's strategy only"
    assert planned["optim"]["means_lr"] == pytest.approx(config.optim.means_lr * 2 ** 0.5)
    saved, again = read_record(record)
    assert again == plan and saved == dataclasses.replace(config, named=saved.named)


def test_a_hand_edited_plan_is_one_line_naming_the_value():
    config = TrainConfig(data=DEMO, steps=3000)
    record = json.loads(json.dumps(run_record(config, initial_plan(config))))
    edits = [({**record["plan"], "steps": "many"}, 'config.json: plan.steps is "many", not a whole number'),
             ({**record["plan"], "mcmc": {**record["plan"]["mcmc"], "cap_max": 1.5}},
              "config.json: plan.mcmc.cap_max is 1.5, not a whole number"),
             ({key: value for key, value in record["plan"].items() if key != "sh_degree"},
              "config.json: plan lacks sh_degree"),
             ({**record["plan"], "speed": 3}, "config.json: unknown option 'plan.speed'"),
             ({**record["plan"], "mcmc": {k: v for k, v in record["plan"]["mcmc"].items() if k != "grow_rate"}},
              "config.json: plan.mcmc lacks grow_rate"),
             ({key: value for key, value in record["plan"].items() if key != "mcmc"}, "config.json: plan lacks mcmc"),
             ([], "config.json: plan must be an object")]
    for edited, message in edits:
        with pytest.raises(MCSplatError, match="put back|another mcsplat|must be an object") as refused:
            read_record({**record, "plan": edited})
        assert str(refused.value).startswith(message) and "\n" not in str(refused.value), str(refused.value)


def old_layout(record: dict) -> dict:
    """config.json as mcsplat wrote it before the plan had a type of its own: the run's decisions were options,
    world_size, schedule_fitted and budget_plan between dist_timeout and model."""
    record = options_with_plan(*read_record(record))
    decided = {"world_size": record["world_size"], "schedule_fitted": True, "budget_plan": record["budget_plan"]}
    old = {}
    for key, value in record.items():
        if key == "model":
            old.update(decided)
        if key not in decided:
            old[key] = value
    return old


class StopAt(Subscriber):
    """Asks the run to stop after step `step` (as Ctrl-C does): it writes a checkpoint and says how to resume."""

    def __init__(self, step: int):
        self.step, self.run = step, None

    def on_run_started(self, event) -> None:
        self.run = event.run

    def on_step_done(self, event) -> None:
        if event.step == self.step:
            self.run.control.stop()


def values_in_the_options_places(record: dict) -> dict:
    """config.json as mcsplat wrote it until 2026-11-28: the plan's values in the options' places, world_size and
    budget_plan beside them, the scene's fingerprint."""
    return {**options_with_plan(*read_record(record)), "scene": record["scene"]}


def both_schedules(record: dict) -> dict:
    """config.json as mcsplat wrote it on 2026-11-28: the plan held ADC's schedule, fitted alike, beside MCMC's."""
    config, plan = read_record(record)
    adc = ADCSchedule.of(config.adc).scaled(plan.steps, PAPER_STEPS)
    return {**record, "plan": {**record["plan"], "adc": to_jsonable(adc)}}


@pytest.mark.parametrize("layout", [old_layout, values_in_the_options_places, both_schedules])
def test_a_run_folder_of_an_older_layout_resumes_bit_for_bit(tmp_path, mini_demo, layout):
    """A run stopped at step 20 whose config.json an older mcsplat wrote continues as the uninterrupted run: its
    fitted schedules are read back as the plan, not fitted a second time (which would stop refinement)."""
    def config(out: Path, **overrides) -> TrainConfig:
        return TrainConfig(data=mini_demo, out=out, steps=40, cap_max=600, downscale=4, quiet=True, save_every=0,
                           save_renders=False, lpips_net="alex", threads=2, model=ModelConfig(num_init_points=300),
                           **overrides)

    train(config(tmp_path / "straight"))
    run = tmp_path / "run"
    with pytest.raises(MCSplatError, match="stopped at step 20"):
        train(config(run), subscribers=[StopAt(20)])
    written = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps(layout(written), indent=2))
    saved, plan = load_run_config(run / "config.json")
    assert (plan.steps, plan.schedule.refine_start, plan.schedule.refine_every, plan.sh_increase_every) == (40, 1, 1, 1)
    assert plan.schedule.grow_rate == written["plan"]["mcmc"]["grow_rate"] > 1.05, "the growth rate --cap-max planned"
    with pytest.raises(dataclasses.FrozenInstanceError):
        saved.steps = 80
    train(config(run, resume=True))
    straight, resumed = load_checkpoint(tmp_path / "straight" / "checkpoint.pt"), load_checkpoint(run / "checkpoint.pt")
    assert resumed["step"] == straight["step"] == 40
    for key, value in straight["model"].items():
        assert torch.equal(resumed["model"][key], value), key


def test_a_plan_made_from_the_options_fits_them_once():
    config = TrainConfig(data=DEMO, steps=3000)
    assert Plan.literal(config).schedule == MCMCSchedule.of(config.mcmc), "the options as they are"
    assert initial_plan(config).schedule.refine_start == 50 and initial_plan(config, 2).steps == 1500
    budget = TrainConfig(data=DEMO, budget="2m")
    assert initial_plan(budget) == Plan.literal(budget), "--budget fits the schedules as it plans"
