"""benchmarks/framework.py: every registered experiment parses its options, declares its arms at toy scale with
valid training options, and reports nothing from an empty folder; the runner runs each arm in its own process,
records it once, and keeps going past an arm that fails; an arm that waits for others (Arm.after) runs after them,
reads their records, and is left out when one failed; a cycle is refused."""

from __future__ import annotations

import dataclasses
import json
import os
import textwrap

import pytest
import tyro

import _common as C
import framework

# Options that keep each experiment's arms small (nothing here runs them).
TOY = {"antialiasing": ["--scenes", "lego", "--steps", "10", "--init-scale", "1.0"],
       "appearance": ["--scenes", "cup", "--steps", "10", "--arms", "none", "affine"],
       "auto_cap": ["--scenes", "lego", "cup", "--caps", "1000", "default", "auto-demand", "--steps", "30"],
       "budget": ["--caps", "1000", "--steps", "10", "--sfm-caps", "2000"],
       "collapse": ["--scene", "/some/where/lego_demo", "--arms", "paper:2000", "auto", "--steps", "20"],
       "defaults_before_after": ["--scenes", "cup", "--steps", "10"],
       "depth_accuracy": ["--arms", "mcmc", "mcmc-surface", "--steps", "10"],
       "fusion_gap": ["--runs", "/some/where/cup-mcmc", "/some/where/cup-adc"],
       "masks": ["--scenes", "cup", "--budget", "10s"],
       "mesh_chamfer": ["--arms", "mcmc", "mcmc-surface", "--steps", "10", "--depth", "planar"],
       "mesh_quality": ["--scenes", "cup", "bird", "--strategies", "mcmc", "adc", "--truncation", "8"],
       "pose_refinement": ["--steps", "10", "--lrs", "1e-3"],
       "sfm_depth": ["--runs", "/some/where/cup-mcmc", "/some/where/bird-adc"],
       "sparse_depth": ["--scenes", "cup", "--seeds", "0", "1", "--steps", "10"],
       "time_to_quality": ["--scenes", "cup", "bird", "--minutes", "1", "2", "--before-minutes", "1"]}
# Arms whose records the scripts made before the runner, in the committed results: found, so not run again.
RECORDED = {"fusion_gap": [], "mesh_chamfer": [], "mesh_quality": ["--scenes", "cup", "bird"], "sfm_depth": [],
            "time_to_quality": ["--scenes", "cup", "bird", "--minutes", "2", "--before-minutes", "2", "--arms",
                                "budget", "before"]}


def options_of(name: str, args: list[str]):
    return tyro.cli(framework.experiment(name).Options, args=args)


def test_every_experiment_has_toy_options():
    assert set(TOY) == set(framework.EXPERIMENTS)


@pytest.mark.parametrize("name", framework.EXPERIMENTS)
def test_help_parses(name, capsys):
    with pytest.raises(SystemExit) as stop:
        tyro.cli(framework.experiment(name).Options, args=["--help"], prog=name)
    assert stop.value.code == 0
    assert "--report" in capsys.readouterr().out


@pytest.mark.parametrize("name", framework.EXPERIMENTS)
def test_arms_at_toy_scale(name, tmp_path):
    module = framework.experiment(name)
    arms = module.arms(options_of(name, TOY[name]))
    assert arms and len({arm.name for arm in arms}) == len(arms)
    assert not any("/" in arm.name for arm in arms)  # a run folder under runs/, not somewhere else
    assert len({tuple(framework.keys(module, arm)) for arm in arms}) == len(arms)  # the records tell them apart
    for arm in arms:
        json.dumps(dataclasses.asdict(arm))  # what the worker is handed
        if arm.config:  # valid training options (data and out are run()'s)
            config = C.make_config(data=tmp_path, out=tmp_path / arm.name, **arm.config)
            assert config.steps in (arm.labels.get("steps"), 30_000)


@pytest.mark.parametrize("name", framework.EXPERIMENTS)
def test_arms_wait_only_for_arms_declared_with_them(name):
    framework.ordered(framework.experiment(name).arms(options_of(name, TOY[name])))  # no ValueError


@pytest.mark.parametrize("name, args", RECORDED.items())
def test_records_made_before_the_runner_are_found(name, args):
    module = framework.experiment(name)
    records = framework.recorded(name, framework.places(name)[0])
    assert all(records.of(*framework.keys(module, arm)) for arm in module.arms(options_of(name, args)))


@pytest.mark.parametrize("name", framework.EXPERIMENTS)
def test_report_of_an_empty_folder(name, tmp_path, capsys):
    args = ["--out", str(tmp_path), "--report"]
    assert framework.run_experiment(name, options_of(name, args), args) == 0
    assert "nothing yet" in capsys.readouterr().err
    assert not (tmp_path / "results.md").exists()


def test_the_records_keep_the_last_of_each_key(tmp_path):
    path = tmp_path / "results.jsonl"
    C.append_jsonl(path, [{"scene": "cup", "steps": 10, "psnr": 1}, {"scene": "bird", "steps": 10, "psnr": 2},
                          {"scene": "cup", "steps": 10, "psnr": 3}])
    records = framework.Records(path, ("scene", "steps"))
    assert [r["psnr"] for r in records.latest()] == [3, 2]
    assert records.get("cup", 10)["psnr"] == 3 and records.get("cup", 20) is None


TOY_EXPERIMENT = '''
from dataclasses import dataclass
from typing import Annotated
import os
import tyro
from framework import Arm, Common, NotReady

KEY = ("n",)


@dataclass(frozen=True)
class Options:
    n: int = 3
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options):
    return [Arm(f"a{i}", {"n": i}, env={"MCSPLAT_TOY": str(i)}) for i in range(options.n)]


def run(arm, options, folder):
    print("said by the run: not the answer")
    if arm.labels["n"] == 1:
        raise RuntimeError("this arm fails")
    if arm.labels["n"] == 2:
        raise NotReady("not this time")
    return {"pid": os.getpid(), "toy": os.environ["MCSPLAT_TOY"]}


def report(records, folder):
    return f"{len(records)} record(s)"
'''


def test_the_runner_records_each_arm_once_from_its_own_process(tmp_path, monkeypatch, capfd):
    (tmp_path / "toy_experiment.py").write_text(textwrap.dedent(TOY_EXPERIMENT))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))  # the workers import it too
    args = ["--out", str(tmp_path / "out")]
    options = options_of("toy_experiment", args)
    assert framework.run_experiment("toy_experiment", options, args) == 1  # a1 failed
    records = C.read_jsonl(tmp_path / "out" / "results.jsonl")
    assert [r["name"] for r in records] == ["a0"]  # a1 failed, a2 was not ready: neither is recorded
    record = records[0]
    assert set(framework.SCHEMA_FIELDS) <= set(record) and record["schema"] == framework.SCHEMA
    assert record["pid"] != os.getpid() and record["toy"] == "0"
    assert record["worker"]["env"]["MCSPLAT_TOY"] == "0" and record["worker"]["peak_rss_mb"] > 0
    assert record["options"]["common"]["out"] == str(tmp_path / "out")
    assert (tmp_path / "out" / "results.md").read_text() == "1 record(s)"
    err = capfd.readouterr().err
    assert "this arm fails" in err and "not this time" in err and "1 arm(s) failed" in err

    # Again, asking only for a0: recorded, so nothing runs.
    args = ["--out", str(tmp_path / "out"), "--n", "1"]
    assert framework.run_experiment("toy_experiment", options_of("toy_experiment", args), args) == 0
    assert len(C.read_jsonl(tmp_path / "out" / "results.jsonl")) == 1
    assert "a0 is recorded" in capfd.readouterr().err


def arm_after(name, *after):
    return framework.Arm(name, {}, after=after)


def test_the_arms_are_ordered_after_the_arms_they_wait_for():
    declared = [arm_after("a"), arm_after("b", "a"), arm_after("c", "d"), arm_after("d"), arm_after("e", "b")]
    assert [a.name for a in framework.ordered(declared)] == ["a", "b", "d", "c", "e"]
    with pytest.raises(ValueError, match="cycle: a, c, d"):
        framework.ordered([arm_after("a", "c"), arm_after("b"), arm_after("c", "d"), arm_after("d", "a")])
    with pytest.raises(ValueError, match="waits for x, which"):
        framework.ordered([arm_after("a", "x")])
    with pytest.raises(ValueError, match="two arms are named a: "):
        framework.ordered([arm_after("a"), arm_after("b"), arm_after("a")])


def test_an_arm_starts_once_the_arms_it_waits_for_are_recorded(capsys):
    started, kept = [], []

    def start(arm):  # in the runner's threads, two at a time
        started.append(arm.name)
        assert set(arm.after) <= set(kept)
        return {"error": "exit status 1"} if arm.name == "a" else {"figures": {}, "worker": {}}

    todo = framework.ordered([arm_after("a"), arm_after("b", "a"), arm_after("c", "d"), arm_after("d"),
                              arm_after("e", "b")])
    assert framework.run_arms("toy", todo, 2, start, lambda arm, answer: kept.append(arm.name)) == 1  # a failed
    assert sorted(started) == ["a", "c", "d"] and kept == ["d", "c"]  # b waits for a, e for b: neither runs
    err = capsys.readouterr().err
    assert "b left out: a not recorded" in err and "e left out: b not recorded" in err


WAITING_EXPERIMENT = '''
from dataclasses import dataclass
from typing import Annotated
import tyro
import framework
from framework import Arm, Common

KEY = ("n",)


@dataclass(frozen=True)
class Options:
    cycle: bool = False
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options):  # declared before the arm it waits for
    return [Arm("a0", {"n": 0}, after=("a1",)), Arm("a1", {"n": 1}, after=("a0",) if options.cycle else ())]


def run(arm, options, folder):
    return {"saw": [r["name"] for r in framework.recorded("waiting_experiment", folder).latest()]}


def report(records, folder):
    return " ".join(r["name"] for r in records)
'''


def test_a_worker_reads_the_records_of_the_arms_it_waits_for(tmp_path, monkeypatch, capfd):
    (tmp_path / "waiting_experiment.py").write_text(textwrap.dedent(WAITING_EXPERIMENT))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))  # the workers import it too
    out = tmp_path / "out"
    args = ["--out", str(out), "--cycle"]
    assert framework.run_experiment("waiting_experiment", options_of("waiting_experiment", args), args) == 2
    assert "cycle: a0, a1" in capfd.readouterr().err and not out.exists()  # refused before anything ran
    args = ["--out", str(out), "--jobs", "2"]
    assert framework.run_experiment("waiting_experiment", options_of("waiting_experiment", args), args) == 0
    records = C.read_jsonl(out / "results.jsonl")
    assert [(r["name"], r["saw"]) for r in records] == [("a1", []), ("a0", ["a1"])]
    assert (out / "results.md").read_text() == "a1 a0"
