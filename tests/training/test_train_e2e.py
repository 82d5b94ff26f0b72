"""End to end on the bundled demo scene: training improves the test PSNR, outputs round-trip, resume is exact."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from mcsplat.config import ModelConfig, TrainConfig, config_of
from mcsplat.data import load_scene
from mcsplat.errors import MCSplatError
from mcsplat.gaussians import GaussianModel
from mcsplat.io.ply import read_ply
from mcsplat.render import render
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.run.evaluation import evaluate
from mcsplat.initialization import initial_model
from mcsplat.run.trained import load
from mcsplat.train import train
from tests.support.helpers import before_each_step, crash_at, signal_at

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


def small_config(out: Path, **overrides) -> TrainConfig:
    options = dict(data=DEMO, out=out, steps=300, quiet=True, lpips_net="alex", save_renders=False, save_every=0,
                   model=ModelConfig(num_init_points=3000),
                   # Refine early so relocation and growth happen within a short test run (steps, not scaled).
                   scale_schedule=False, mcmc=MCMCConfig(cap_max=3400, refine_start=50, refine_every=50))
    options.update(overrides)
    return config_of(**options)


@pytest.fixture(scope="module")
def demo_scene():
    return load_scene(DEMO)


def initial_psnr(config: TrainConfig, scene) -> float:
    generator = torch.Generator().manual_seed(config.seed)
    model, _ = initial_model(config, scene, torch.device("cpu"), generator)
    return evaluate(model, scene.test, scene.background, 0, torch.device("cpu")).psnr


@pytest.mark.parametrize("strategy", ["mcmc", "adc"])
def test_training_improves_test_psnr_and_writes_a_run(tmp_path, demo_scene, strategy, device):
    config = small_config(tmp_path / strategy, strategy=strategy, device=device.type)
    before = initial_psnr(config, demo_scene)
    metrics = train(config)
    assert metrics["psnr"] > before + 4.0, (before, metrics["psnr"])
    run = tmp_path / strategy
    for name in ("config.json", "checkpoint.pt", "metrics.json", "point_cloud.ply", "log.jsonl"):
        assert (run / name).is_file(), name
    written = json.loads((run / "metrics.json").read_text())
    assert {"psnr", "ssim", "lpips", "num_gaussians", "steps", "train_seconds", "device"} <= written.keys()
    assert written["steps"] == 300 and written["device"] == device.type
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [100, 200, 300]
    if strategy == "mcmc":
        assert metrics["num_gaussians"] == 3400, "growth (5% per refine step) must reach cap_max and stop there"


def test_ply_round_trip_renders_the_same_image(tmp_path, demo_scene):
    config = small_config(tmp_path / "run", steps=120)
    train(config)
    model = load(tmp_path / "run", torch.device("cpu")).model
    alive = model.opacities.detach() > 0.005
    kept = GaussianModel(*(model.params[k].detach()[alive] for k in
                           ("means", "log_scales", "quats", "opacity_logits", "sh0", "shN")))
    from_ply = GaussianModel(**read_ply(tmp_path / "run" / "point_cloud.ply"))
    assert from_ply.num_gaussians == int(alive.sum())
    camera = demo_scene.test[0].camera
    with torch.no_grad():
        expected = render(kept, camera, (1.0, 1.0, 1.0), 3).rgb
        actual = render(from_ply, camera, (1.0, 1.0, 1.0), 3).rgb
    assert torch.equal(actual, expected)


def final_params(run: Path) -> dict[str, torch.Tensor]:
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    return {k: v for k, v in state["model"].items()}


def test_resume_after_a_crash_and_after_ctrl_c_matches_an_uninterrupted_run(tmp_path, monkeypatch):
    steps = 200
    train(small_config(tmp_path / "straight", steps=steps))
    expected = final_params(tmp_path / "straight")

    # A crash between checkpoints: the last periodic checkpoint (step 100) is what survives.
    with monkeypatch.context() as patch:
        before_each_step(patch, crash_at(130))
        with pytest.raises(RuntimeError, match="simulated crash"):
            train(small_config(tmp_path / "crashed", steps=steps, save_every=100))
    # A kill during a checkpoint write would also leave its temporary file: resume removes it.
    leftover = tmp_path / "crashed" / ".checkpoint.k1ll3d_x.tmp.pt"
    leftover.write_bytes(b"half a checkpoint")
    train(small_config(tmp_path / "crashed", steps=steps, save_every=100, resume=True))
    assert not leftover.exists()
    resumed = final_params(tmp_path / "crashed")
    assert resumed.keys() == expected.keys()
    for key in expected:
        assert torch.equal(resumed[key], expected[key]), key

    # Ctrl-C: the step finishes, a checkpoint is written, and the run stops with a hint to resume.
    with monkeypatch.context() as patch:
        before_each_step(patch, signal_at(77, signal.SIGINT))
        with pytest.raises(MCSplatError, match="stopped at step 78.*--resume"):
            train(small_config(tmp_path / "interrupted", steps=steps))
    # The saved configuration rules on resume: a different --steps on the command line is ignored. A run folder
    # moved elsewhere continues where it now is.
    (tmp_path / "interrupted").rename(tmp_path / "moved")
    train(small_config(tmp_path / "moved", steps=30_000, resume=True))
    assert not (tmp_path / "interrupted").exists()
    resumed = final_params(tmp_path / "moved")
    for key in expected:
        assert torch.equal(resumed[key], expected[key]), key


def test_an_existing_run_is_never_overwritten_silently(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    with pytest.raises(MCSplatError, match="already holds a run"):
        train(small_config(run, steps=5))
    assert (run / "config.json").read_text() == "{}"
    with pytest.raises(MCSplatError, match="no checkpoint.pt"):
        train(small_config(tmp_path / "fresh", steps=5, resume=True))


def test_cli_train_eval_render_export(tmp_path):
    run = tmp_path / "cli"
    mcsplat = [sys.executable, "-m", "mcsplat.cli"]
    done = subprocess.run(mcsplat + ["train", str(DEMO), "--out", str(run), "--steps", "30", "--quiet",
                                     "--model.num-init-points", "1000", "--lpips-net", "alex",
                                     "--no-save-renders"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "" and [line.split()[0] for line in done.stdout.splitlines()] == ["test", "wrote", "wrote"], \
        "--quiet prints the result alone"
    trained = json.loads((run / "metrics.json").read_text())
    (run / "metrics.json").write_text(json.dumps({**trained, "per_view_psnr": {"stale": 1.0}}))
    done = subprocess.run(mcsplat + ["eval", str(run), "--lpips-net", "alex"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0 and "PSNR" in done.stdout, done.stderr
    evaluated = json.loads((run / "metrics.json").read_text())
    assert evaluated["per_view_psnr"] == trained["per_view_psnr"], "eval writes the views' PSNR it measured"
    done = subprocess.run(mcsplat + ["render", str(run), "--video", "--frames", "6", "--fps", "3"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (run / "renders" / "test.mp4").stat().st_size > 1000
    done = subprocess.run(mcsplat + ["export", str(run), "--out", str(tmp_path / "x.ply")], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0 and (tmp_path / "x.ply").is_file(), done.stderr
    # Bad input: one line on stderr, exit code 2 (the four in one process: each start costs seconds).
    cases = [["train", str(tmp_path / "nowhere")], ["eval", str(tmp_path)], ["train", str(DEMO), "--steps", "0"],
             ["train", str(DEMO), "--out", str(run)]]
    script = ("import json, sys; from mcsplat.cli import main; "
              "print(json.dumps([main(args) for args in json.loads(sys.argv[1])]))")
    done = subprocess.run([sys.executable, "-c", script, json.dumps(cases)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0 and json.loads(done.stdout) == [2] * len(cases), done.stderr
    errors = done.stderr.splitlines()
    assert len(errors) == len(cases) and all(line.startswith("mcsplat: error:") for line in errors), errors


def test_quiet_still_prints_the_final_scores_and_the_files_written(tmp_path, mini_demo, capsys):
    """--quiet is for scripts, which still want the result: the progress goes, the scores and files stay."""
    from mcsplat.cli import main

    run = tmp_path / "run"
    assert main(["train", str(mini_demo), "--out", str(run), "--steps", "10", "--eval-every", "5", "--quiet",
                 "--model.num-init-points", "2000", "--lpips-net", "alex"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith("test PSNR ") and " on 3 views; " in lines[0], lines
    assert lines[1].startswith(f"wrote {run / 'point_cloud.ply'} (") and lines[1].endswith(f"{run / 'metrics.json'}")
    assert lines[2] == f"wrote {run / 'report.html'}"
    assert "step 5: test PSNR" not in captured.out + captured.err and "%|" not in captured.err, "no progress"
