"""What mcsplat guarantees about a run folder (README, "What mcsplat guarantees"): one writer at a time, checkpoints
that are checked and kept one deep, saved on SIGTERM and by time, a log that matches the checkpoint."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from mcsplat import subscribers
from mcsplat.cli import main
from mcsplat.config import to_jsonable
from mcsplat.errors import MCSplatError
from mcsplat.io.checkpoint import load_checkpoint, save_checkpoint
from mcsplat.run.folder import render_file
from mcsplat.strategy.adc import ADCSchedule
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.train import train
from tests.support.helpers import before_each_step, crash_at, signal_at
from tests.training.test_train_e2e import small_config

HOLD_LOCK = """
import sys, time
from mcsplat.io.lock import FolderLock
FolderLock(sys.argv[1], "mcsplat train").acquire()
print("held", flush=True)
time.sleep(120)
"""


class LockHolder:
    """Another process holding a run folder's lock, as a second `mcsplat train` would."""

    def __init__(self, run: Path):
        run.mkdir(parents=True, exist_ok=True)
        self.process = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(run / ".lock")], stdout=subprocess.PIPE,
                                        text=True)
        assert self.process.stdout.readline().strip() == "held"

    def kill(self) -> None:
        """Dies without a word (SIGKILL): its lock file stays behind, stale."""
        self.process.kill()
        self.process.wait()


def mini_config(scene: Path, out: Path, **overrides):
    """small_config (tests/training/test_train_e2e.py) on the mini demo scene (conftest.py)."""
    return small_config(out, data=scene, **overrides)


@pytest.fixture
def run_copy(tiny_run, tmp_path) -> Path:
    return Path(shutil.copytree(tiny_run, tmp_path / "run"))


def test_a_second_writer_of_a_run_folder_gets_a_one_line_error(tmp_path, run_copy, mini_demo, capsys):
    run = tmp_path / "busy"
    holder = LockHolder(run)
    try:
        with pytest.raises(MCSplatError, match=rf"busy is in use by mcsplat train \(pid {holder.process.pid}"):
            train(mini_config(mini_demo, run, steps=5))
        assert sorted(p.name for p in run.iterdir()) == [".lock"], "the refused run wrote nothing"
    finally:
        holder.kill()
    # The lock of a process that died is stale: the next run takes it over, and leaves no lock behind.
    assert (run / ".lock").exists()
    train(mini_config(mini_demo, run, steps=5))
    assert (run / "checkpoint.pt").is_file() and not (run / ".lock").exists()

    (run_copy / "point_cloud.spz").unlink(missing_ok=True)  # another test may have exported one into tiny_run
    holder = LockHolder(run_copy)
    try:
        for command in (["eval", str(run_copy)], ["export", str(run_copy), "--format", "spz"],
                        ["report", str(run_copy)], ["render", str(run_copy)]):
            capsys.readouterr()
            assert main(command) == 2, command
            error = capsys.readouterr().err
            assert error.startswith("mcsplat: error:") and error.count("\n") == 1, error
            assert "is in use by mcsplat train" in error, error
        assert not (run_copy / "point_cloud.spz").exists()
    finally:
        holder.kill()


def test_the_previous_checkpoint_is_kept_and_a_damaged_one_is_refused(tmp_path, mini_demo, capsys):
    run = tmp_path / "run"
    train(mini_config(mini_demo, run, steps=30, save_every=10))
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 30
    assert load_checkpoint(run / "checkpoint.prev.pt")["step"] == 20
    # Damage the tensor bytes of the checkpoint, keeping the archive readable.
    state = load_checkpoint(run / "checkpoint.pt")
    means = state["model"]["params.means"]
    data = (run / "checkpoint.pt").read_bytes()
    where = data.find(means.numpy().tobytes()[:64])
    assert where > 0
    damaged = bytearray(data)
    damaged[where + 3] ^= 0x40
    (run / "checkpoint.pt").write_bytes(bytes(damaged))
    for command in (["eval", str(run)], ["export", str(run), "--out", str(tmp_path / "x.ply")]):
        capsys.readouterr()
        assert main(command) == 2
        error = capsys.readouterr().err
        assert "damaged checkpoint" in error and "checkpoint.prev.pt" in error and error.count("\n") == 1, error
    assert not (tmp_path / "x.ply").exists()
    (run / "checkpoint.prev.pt").replace(run / "checkpoint.pt")  # what the message advises
    assert main(["export", str(run), "--out", str(tmp_path / "x.ply")]) == 0


@pytest.mark.parametrize("options", [[], ["--out", "x.spz"], ["--format", "mesh"],
                                     ["--format", "mesh", "--out", "x.glb"]])
def test_export_refuses_parameters_that_are_not_finite_in_every_format(run_copy, tmp_path, options, capsys):
    """One check for every format: a mesh of a diverged run is refused as its splats are."""
    state = load_checkpoint(run_copy / "checkpoint.pt")
    state["model"]["params.means"][7, 1] = float("inf")
    save_checkpoint(run_copy / "checkpoint.pt", {k: v for k, v in state.items() if k != "version"})
    before = sorted(p.name for p in run_copy.iterdir()), (run_copy / "point_cloud.ply").read_bytes()
    options = [str(tmp_path / option) if option.startswith("x.") else option for option in options]
    capsys.readouterr()
    assert main(["export", str(run_copy), *options]) == 2
    error = capsys.readouterr().err
    assert "NaN or infinite values in means" in error and error.count("\n") == 1, error
    assert (sorted(p.name for p in run_copy.iterdir()), (run_copy / "point_cloud.ply").read_bytes()) == before
    assert not list(tmp_path.glob("x.*"))


@pytest.fixture
def sigterm_reaches_no_default():
    """SIGTERM's default handler would end this test process: make it an error the test sees instead."""
    def not_handled(signum, frame):
        raise AssertionError("SIGTERM was not handled by the training run")

    previous = signal.signal(signal.SIGTERM, not_handled)
    yield
    signal.signal(signal.SIGTERM, previous)


def test_sigterm_saves_a_checkpoint_then_stops(tmp_path, mini_demo, monkeypatch, sigterm_reaches_no_default):
    before_each_step(monkeypatch, signal_at(37, signal.SIGTERM))
    with pytest.raises(MCSplatError, match="stopped at step 38.*--resume"):
        train(mini_config(mini_demo, tmp_path / "run", steps=200))
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["step"] == 38
    assert signal.getsignal(signal.SIGTERM).__name__ == "not_handled", "the run puts the handler back"


def test_checkpoints_are_also_written_by_time(tmp_path, mini_demo, monkeypatch):
    clock = {"now": 0.0}
    monkeypatch.setattr(subscribers, "time", SimpleNamespace(monotonic=lambda: clock["now"]))

    def slow_step(step: int) -> None:
        clock["now"] += 7.0  # seconds per step
        crash_at(45)(step)

    before_each_step(monkeypatch, slow_step)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(mini_config(mini_demo, tmp_path / "run", steps=200, save_every=0, save_every_minutes=2.0))
    # 2 minutes are 18 steps of 7 s: a checkpoint at step 18 and at step 36.
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["step"] == 36
    assert load_checkpoint(tmp_path / "run" / "checkpoint.prev.pt")["step"] == 18
    assert small_config(tmp_path / "x").save_every_minutes == 10.0, "by default every 10 minutes"


def logged_steps(run: Path) -> list[int]:
    return [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]


def test_the_log_matches_the_run_after_overwrite_and_after_a_resume(tmp_path, mini_demo, monkeypatch):
    run = tmp_path / "run"
    train(mini_config(mini_demo, run, steps=30, save_every=10))
    assert logged_steps(run) == [30] and (run / "checkpoint.prev.pt").is_file()
    # --overwrite: a new log, and no checkpoint of the old run left to fall back to.
    train(mini_config(mini_demo, run, steps=20, overwrite=True))
    assert logged_steps(run) == [20]
    assert not (run / "checkpoint.prev.pt").exists() and load_checkpoint(run / "checkpoint.pt")["step"] == 20

    # Killed at step 50, after the evaluation of step 40 was logged but with the checkpoint of step 30: the resumed
    # run logs step 40 again, once.
    before_each_step(monkeypatch, crash_at(50))
    config = dict(steps=60, eval_every=40, save_every=30)
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(mini_config(mini_demo, tmp_path / "killed", **config))
    assert logged_steps(tmp_path / "killed") == [40]
    with (tmp_path / "killed" / "log.jsonl").open("a") as log:
        log.write('{"step": 41, "loss"')  # a record cut short by the kill
    monkeypatch.undo()
    train(mini_config(mini_demo, tmp_path / "killed", resume=True, **config))
    assert logged_steps(tmp_path / "killed") == [40, 60]


def test_renders_of_views_with_one_file_name_in_two_folders_are_all_kept(tiny_run, tmp_path, capsys):
    """The demo's train/r_0 and test/r_0: rendered into one folder, each keeps its render."""
    out = tmp_path / "renders"
    for split in ("test", "train"):
        assert main(["render", str(tiny_run), "--split", split, "--out", str(out)]) == 0
    pngs = sorted(str(p.relative_to(out)) for p in out.rglob("*.png"))
    assert len(pngs) == 125 and "test/r_0.png" in pngs and "train/r_0.png" in pngs
    assert render_file(out, "../../a/./b") == out / "a" / "b.png", "nothing is written outside the folder"


def test_a_cap_below_the_initial_points_is_kept_from_the_start(tmp_path, mini_demo):
    notes = []
    metrics = train(mini_config(mini_demo, tmp_path / "run", steps=5, mcmc=MCMCConfig(cap_max=500)),
                    subscribers=[lambda event: notes.append(getattr(event, "init_note", None))])
    assert metrics["num_gaussians"] == 500
    note = next(note for note in notes if note)
    assert note.startswith("random (3,000 points")
    assert "500 of the 3,000 kept at random to stay within --cap-max" in note


def test_a_hand_edited_config_is_refused_on_resume_in_one_line(tmp_path, mini_demo, capsys):
    run = tmp_path / "run"
    train(mini_config(mini_demo, run, steps=10))
    written = json.loads((run / "config.json").read_text())
    edits = [({"steps": "300"}, 'config.json: steps is "300", not a whole number'),
             ({"mcmc": {**written["mcmc"], "cap_max": "many"}}, 'config.json: mcmc.cap_max is "many"'),
             ({"optim": {**written["optim"], "betas": [0.9]}}, "optim.betas is [0.9], not a list of 2 values"),
             ({"mcmc": {**written["mcmc"], "cap_max": -5}}, "config.json: mcmc.cap_max must be a whole number"),
             ({"strategy": "adc"}, 'config.json: strategy is "adc", but checkpoint.pt was trained with "mcmc"'),
             ({"strategy": "adc", "plan": {**written["plan"], "adc": to_jsonable(ADCSchedule())}},  # as of 2026-11-28
              'config.json: strategy is "adc", but checkpoint.pt was trained with "mcmc"'),
             ({"model": {**written["model"], "sh_degree": 1}}, "config.json: model.sh_degree is 1, but checkpoint.pt")]
    for edit, expected in edits:
        (run / "config.json").write_text(json.dumps({**written, **edit}))
        capsys.readouterr()
        assert main(["train", str(mini_demo), "--out", str(run), "--resume", "--quiet"]) == 2, edit
        error = capsys.readouterr().err
        assert error.startswith("mcsplat: error:") and expected in error and error.count("\n") == 1, error


def test_a_scene_folder_is_never_a_run_folder(tmp_path, mini_demo):
    scene = Path(shutil.copytree(mini_demo, tmp_path / "scene"))
    other = Path(shutil.copytree(mini_demo, tmp_path / "other"))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    for out, expected in ((scene, "is inside the scene folder"), (scene / "runs" / "a", "is inside the scene folder"),
                          (other, "holds a blender scene"),
                          (other / "images" / "a", "is inside .*other, which holds a blender scene")):
        with pytest.raises(MCSplatError, match=expected):
            train(mini_config(scene, out, steps=5))
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before, "nothing written into a scene"


def _run_on(run: Path, scene: Path) -> Path:
    """The run's config.json pointed at `scene` (a copy of the scene it trained on, cut down as a test needs)."""
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "data": str(scene)}))
    return run


def test_a_video_through_a_single_camera_is_a_one_line_error(run_copy, mini_demo, tmp_path, capsys):
    scene = Path(shutil.copytree(mini_demo, tmp_path / "scene"))
    meta = json.loads((scene / "transforms_test.json").read_text())
    (scene / "transforms_test.json").write_text(json.dumps({**meta, "frames": meta["frames"][:1]}))
    run = _run_on(run_copy, scene)
    assert main(["render", str(run), "--video", "--frames", "4"]) == 2
    error = capsys.readouterr().err
    assert error.startswith("mcsplat: error:") and "at least two cameras" in error and error.count("\n") == 1, error
    assert not (run / "renders" / "test.mp4").exists()


def test_a_run_without_test_views_finishes_without_test_scores(tmp_path, mini_demo, capsys):
    """--test-every 0 on a scene without a test split: the run ends with its .ply, metrics.json and report, and
    says that there are no test scores; periodic evaluations are left out, saying so once."""
    scene = Path(shutil.copytree(mini_demo, tmp_path / "scene"))
    (scene / "transforms_test.json").unlink()
    run = tmp_path / "run"
    assert main(["train", str(scene), "--out", str(run), "--test-every", "0", "--steps", "10", "--eval-every", "5",
                 "--model.num-init-points", "500", "--lpips-net", "alex", "--no-save-renders"]) == 0
    captured = capsys.readouterr()
    assert "no test views" in captured.out and f"wrote {run / 'point_cloud.ply'}" in captured.out
    warned = [line for line in captured.err.splitlines() if line.startswith("mcsplat: warning:")]
    assert len(warned) == 1 and "--eval-every" in warned[0], captured.err
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["test_views"] == 0 and metrics["psnr"] is None and metrics["steps"] == 10
    assert (run / "point_cloud.ply").is_file() and (run / "report.html").is_file()
    assert main(["eval", str(run)]) == 2
    error = capsys.readouterr().err
    assert "no test views" in error and error.count("\n") == 1


def test_resume_refuses_the_options_it_would_ignore(tmp_path, mini_demo, capsys):
    """--resume continues a run with the options it was trained with: one that says otherwise is refused, naming
    it, before anything changes; the run's own options repeated are fine."""
    run = tmp_path / "run"
    trained = ["train", str(mini_demo), "--out", str(run), "--steps", "10", "--pose-opt", "--antialiased", "--quiet",
               "--model.num-init-points", "2000", "--lpips-net", "alex", "--no-save-renders"]
    assert main(trained) == 0
    files = {path.name: path.stat().st_mtime_ns for path in run.iterdir()}
    resume = ["train", str(mini_demo), "--out", str(run), "--resume", "--quiet"]
    cases = [(["--budget", "5s"], "--budget 5s (trained with --budget None)"),
             (["--appearance", "affine"], "--appearance affine (trained with --appearance none)"),
             (["--no-pose-opt"], "--no-pose-opt (trained with --pose-opt)"),
             (["--no-antialiased", "--steps", "100"],
              "--no-antialiased (trained with --antialiased), --steps 100 (trained with --steps 10)")]
    for options, ignored in cases:
        capsys.readouterr()
        assert main(resume + options) == 2, options
        assert capsys.readouterr().err == f"mcsplat: error: --resume continues the run with the options it was " \
            f"trained with ({run / 'config.json'}), so these would be ignored: {ignored}; leave them out, or start a " \
            f"new run with --overwrite or another --out\n"
        assert {path.name: path.stat().st_mtime_ns for path in run.iterdir()} == files, options
    assert main(trained + ["--resume"]) == 0, "the options it was trained with"
    assert main(resume) == 0


def test_sigterm_during_the_final_evaluation_says_how_to_finish(tmp_path, mini_demo, monkeypatch, capsys,
                                                               sigterm_reaches_no_default):
    """The steps are done and checkpointed: the run stops with one line and its lock released, and --resume makes
    the scores, point_cloud.ply and the report."""
    from mcsplat import trainer

    evaluate = trainer.evaluate

    def terminated(*args, **kwargs):
        signal.raise_signal(signal.SIGTERM)
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(trainer, "evaluate", terminated)
    run = tmp_path / "run"
    command = ["train", str(mini_demo), "--out", str(run), "--steps", "10", "--quiet", "--model.num-init-points",
               "2000", "--lpips-net", "alex"]
    assert main(command) == 2
    assert capsys.readouterr().err == f"mcsplat: error: stopped at step 10 while finishing the run (its final " \
        f"evaluation, point_cloud.ply, metrics.json and report); the checkpoint is saved: finish it with `mcsplat " \
        f"train {mini_demo} --out {run} --resume`\n"
    assert sorted(path.name for path in run.iterdir()) == ["checkpoint.pt", "config.json", "log.jsonl"]
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 10
    assert signal.getsignal(signal.SIGTERM).__name__ == "not_handled", "the run puts the handler back"
    monkeypatch.setattr(trainer, "evaluate", evaluate)
    assert main(command + ["--resume"]) == 0
    assert {"point_cloud.ply", "metrics.json", "report.html"} <= {path.name for path in run.iterdir()}
    assert json.loads((run / "metrics.json").read_text())["steps"] == 10


def test_a_refused_run_leaves_no_folder_it_made(tmp_path, mini_demo):
    """A run refused after its folder was made (here: its scene is gone) removes the folders it made, and only
    those: a folder that was there stays, with what it held."""
    gone = tmp_path / "gone"
    with pytest.raises(MCSplatError, match="does not exist"):
        train(mini_config(gone, tmp_path / "runs" / "a" / "run", steps=5))
    assert not (tmp_path / "runs").exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    for out in (mine, mine / "run"):
        with pytest.raises(MCSplatError, match="does not exist"):
            train(mini_config(gone, out, steps=5))
    assert [path.name for path in mine.iterdir()] == ["notes.txt"]


def _float_options() -> list[tuple[str, str]]:
    """(group, name) of every float option of `mcsplat train` (its own, its model group's, and those of the groups
    whose flags have no prefix: --surface-*, --depth-*, ...): inf passed each range check without an upper end
    (--surface-flatten, --surface-normal, --surface-distortion...)."""
    import typing

    from mcsplat.config import ModelConfig, TrainConfig
    from mcsplat.typed_json import flat_groups, option_types

    hints = typing.get_type_hints(TrainConfig)
    owners = [("", TrainConfig), ("model", ModelConfig)] + [("", hints[group]) for group in flat_groups(TrainConfig)]
    return [(group, name) for group, cls in owners
            for name, hint in option_types(cls).items() if float in (hint, *getattr(hint, "__args__", ()))]


@pytest.mark.parametrize("value", [float("inf"), float("nan")])
def test_every_float_option_refuses_a_number_that_is_not_finite(value):
    from dataclasses import replace

    import torch

    from mcsplat.config import ModelConfig, TrainConfig, with_options
    from mcsplat.mesh import MeshOptions
    from mcsplat.mesh.grid import choose_grid

    options = _float_options()
    assert {"surface_flatten", "surface_normal", "surface_distortion", "init_extent"} <= {n for _, n in options}
    base = TrainConfig(data=Path("scene"))
    for group, name in options:
        with pytest.raises(MCSplatError, match=f"--{group + '.' if group else ''}{name.replace('_', '-')} {value}: "
                                               "not a finite number"):
            if group:
                replace(base, model=replace(ModelConfig(), **{name: value}))
            else:
                with_options(base, **{name: value})
    with pytest.raises(MCSplatError, match="--truncation must be at least 1"):
        MeshOptions(truncation=value)
    with pytest.raises(MCSplatError, match="--voxel-size must be a positive finite number"):
        choose_grid(torch.zeros(3), torch.ones(3), value, 1 << 20)


def test_a_loss_that_is_not_finite_claims_no_checkpoint(tmp_path, mini_demo, monkeypatch):
    """The advice said "the last checkpoint is kept" at step 0, where there is none."""
    from mcsplat import step

    monkeypatch.setattr(step, "total_loss", lambda terms, context: context.rgb.sum() * float("inf"))
    with pytest.raises(MCSplatError, match="step 0: the loss became inf") as refused:
        train(mini_config(mini_demo, tmp_path / "run", steps=5))
    assert "checkpoint" not in str(refused.value)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_surface_options_without_surface_are_refused(tmp_path, mini_demo, capsys):
    run = tmp_path / "run"
    cheap = ["--steps", "1", "--quiet", "--model.num-init-points", "500", "--lpips-net", "alex", "--no-save-renders"]
    assert main(["train", str(mini_demo), "--out", str(run), "--surface-flatten", "50", "--surface-from", "0.5"]
                + cheap) == 2
    assert capsys.readouterr().err == "mcsplat: error: --surface-flatten 50.0, --surface-from 0.5: the --surface-* " \
        "options shape the loss terms of --surface and the mesh it ends with, which this run trains without, so " \
        "they would be ignored; add --surface, or leave them out\n"
    assert not run.exists()


def test_config_json_whose_caps_disagree_with_cap_max_is_refused():
    """A number in cap_max sets mcmc.cap_max (and adc.cap_max, mcmc.auto_cap): another value there, edited by hand,
    was overridden without a word. A --budget run's file holds its plan's cap there, which stays allowed."""
    from mcsplat.config import TrainConfig
    from mcsplat.planning import Plan, read_record, run_record

    config = TrainConfig(data=Path("scene"), cap_max=5000)
    record = json.loads(json.dumps(run_record(config, Plan.literal(config))))
    assert read_record(record)[0].mcmc.cap_max == 5000
    for group, key, value in (("mcmc", "cap_max", 8000), ("adc", "cap_max", 3000), ("mcmc", "auto_cap", True)):
        edited = {**record, group: {**record[group], key: value}}
        with pytest.raises(MCSplatError, match=f"config.json: {group}.{key} is {json.dumps(value)}, but cap_max 5000 "
                                               f"makes it"):
            read_record(edited)
    budget = TrainConfig(data=Path("scene"), cap_max=5000, budget="10m")
    planned = {**json.loads(json.dumps(run_record(budget, Plan.literal(budget))))}
    planned["mcmc"] = {**planned["mcmc"], "cap_max": 3000}
    read_record(planned)  # the plan's cap, below cap_max: read as it is
    with pytest.raises(MCSplatError, match="mcmc.cap_max is 9000"):
        read_record({**planned, "mcmc": {**planned["mcmc"], "cap_max": 9000}})
