"""SIGTERM (kill, timeout, docker, SLURM) and SIGHUP (a closed terminal) stop every command as Ctrl-C does: one
mcsplat line, the folder's lock released, nothing half-made left behind (issue 58)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mcsplat.cli import main
from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.errors import MCSplatError
from mcsplat.io.checkpoint import load_checkpoint
from mcsplat.train import train
from tests.support.helpers import before_each_step, demo_photos_scene, signal_at
from tests.run.test_run_folder import mini_config

REPO = Path(__file__).resolve().parents[2]

SIGNAL_IN_EVAL = """
import os, signal, sys, time
import mcsplat.run.evaluation

def evaluate(*args, **kwargs):  # the run and its COLMAP scene are loaded: pycolmap is imported
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(30)

mcsplat.run.evaluation.evaluate = evaluate
from mcsplat.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture
def signals_reach_no_default():
    """SIGTERM's and SIGHUP's default handlers would end this test process: make them an error the test sees."""
    def not_handled(signum, frame):
        raise AssertionError(f"{signal.Signals(signum).name} was not handled")

    previous = {number: signal.signal(number, not_handled) for number in (signal.SIGTERM, signal.SIGHUP)}
    yield
    for number, handler in previous.items():
        signal.signal(number, handler)


def small_colmap_scene(shared_data: Path, root: Path, count: int = 6) -> Path:
    """A COLMAP scene of the bird's first `count` photos, with 2,000 of its points (tracks left out)."""
    import pycolmap

    bird = shared_data / "colmap_bird"
    full = pycolmap.Reconstruction(str(bird / "sparse" / "0"))
    small = pycolmap.Reconstruction()
    (root / "images").mkdir(parents=True)
    for image in sorted(full.images.values(), key=lambda image: image.name)[:count]:
        if not small.exists_camera(image.camera_id):
            small.add_camera_with_trivial_rig(full.cameras[image.camera_id])
        small.add_image_with_trivial_frame(pycolmap.Image(name=image.name, camera_id=image.camera_id,
                                                          image_id=image.image_id), image.cam_from_world())
        shutil.copyfile(bird / "images" / image.name, root / "images" / image.name)
    for point in list(full.points3D.values())[:2000]:
        small.add_point3D(point.xyz, pycolmap.Track(), point.color)
    (root / "sparse" / "0").mkdir(parents=True)
    small.write_binary(str(root / "sparse" / "0"))
    return root


def test_sigterm_in_eval_of_a_colmap_run_is_one_line(shared_data, tmp_path):
    """pycolmap's glog dumped about 30 lines of C++ stack on SIGTERM, and no mcsplat line."""
    scene = small_colmap_scene(shared_data, tmp_path / "bird")
    run = tmp_path / "run"
    train(TrainConfig(data=scene, out=run, steps=2, downscale=8, quiet=True, lpips_net="alex", save_renders=False,
                      save_every=0, model=ModelConfig(num_init_points=500)))
    metrics = (run / "metrics.json").read_bytes()
    done = subprocess.run([sys.executable, "-c", SIGNAL_IN_EVAL, "eval", str(run)], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert done.returncode == 130, done.stderr
    assert done.stderr.splitlines() == ["mcsplat: interrupted"], done.stderr
    assert not (run / ".lock").exists() and (run / "metrics.json").read_bytes() == metrics


def test_sigterm_before_the_first_step_leaves_a_folder_that_says_how_to_start_again(tmp_path, mini_demo, capsys,
                                                                                   monkeypatch,
                                                                                   signals_reach_no_default):
    """config.json is written, the kernels are being compiled: the run stops with one line, and the folder without a
    checkpoint asks for --overwrite (it asked for --resume, which then found no checkpoint)."""
    from mcsplat import trainer

    def terminated(*args, **kwargs):
        signal.raise_signal(signal.SIGTERM)

    monkeypatch.setattr(trainer, "compile_kernels", terminated)
    run = tmp_path / "run"
    command = ["train", str(mini_demo), "--out", str(run), "--steps", "3", "--quiet", "--model.num-init-points",
               "500", "--lpips-net", "alex", "--no-save-renders"]
    assert main(command) == 130
    assert capsys.readouterr().err == "mcsplat: interrupted\n"
    assert sorted(path.name for path in run.iterdir()) == ["config.json"], "no lock left"
    assert signal.getsignal(signal.SIGTERM).__name__ == "not_handled", "the handler is put back"
    monkeypatch.undo()
    for extra in ([], ["--resume"]):
        assert main(command + extra) == 2
        error = capsys.readouterr().err
        assert error.count("\n") == 1 and "no checkpoint.pt" in error and "--overwrite" in error, error
        assert "pass --resume" not in error, error
    assert main(command + ["--overwrite"]) == 0
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 3


def test_sighup_while_the_points_are_triangulated_leaves_no_folder(tmp_path, capsys, monkeypatch,
                                                                     signals_reach_no_default):
    """A closed terminal while a scene without SfM points is triangulated (before: the process ended without a word,
    its run folder and lock left behind): one line, and the folders the run made are removed."""
    from mcsplat import initialization

    scene, _ = demo_photos_scene(tmp_path / "photos", 4)

    def hung_up(*args, **kwargs):
        signal.raise_signal(signal.SIGHUP)
        raise AssertionError("SIGHUP did not stop the run")

    monkeypatch.setattr(initialization, "triangulated_points", hung_up)
    assert main(["train", str(scene), "--out", str(tmp_path / "runs" / "a"), "--steps", "3", "--quiet"]) == 130
    assert capsys.readouterr().err == "mcsplat: interrupted\n"
    assert not (tmp_path / "runs").exists()
    assert signal.getsignal(signal.SIGHUP).__name__ == "not_handled", "the handler is put back"


def test_sighup_while_training_saves_a_checkpoint_then_stops(tmp_path, mini_demo, monkeypatch,
                                                              signals_reach_no_default):
    before_each_step(monkeypatch, signal_at(3, signal.SIGHUP))
    with pytest.raises(MCSplatError, match="stopped at step 4.*--resume"):
        train(mini_config(mini_demo, tmp_path / "run", steps=50))
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["step"] == 4


def test_a_run_folder_without_a_checkpoint_asks_for_overwrite(tmp_path, mini_demo):
    """A run killed (SIGKILL, a crash) before its first checkpoint: --resume has nothing to continue, so neither
    refusal may suggest it."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": str(mini_demo)}))
    for resume in (False, True):
        with pytest.raises(MCSplatError) as refused:
            train(mini_config(mini_demo, run, steps=3, resume=resume))
        message = str(refused.value)
        assert "no checkpoint.pt" in message and "--overwrite" in message and "pass --resume" not in message
    with pytest.raises(MCSplatError, match=f"--resume: {tmp_path / 'none'} holds no run"):
        train(mini_config(mini_demo, tmp_path / "none", steps=3, resume=True))
    assert not (tmp_path / "none").exists()
    assert os.listdir(run) == ["config.json"]
