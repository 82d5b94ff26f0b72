"""--resume continues on the scene the run trained on: config.json names it from the root, with a fingerprint (its
kind, its views' names and image sizes) by which the scene given on the command line is known wherever it is now;
another scene is refused (issue 58: a lego model went on training on the cup, and `train cup --resume` on a lego
run trained lego without a word)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from mcsplat.run import start as run_start
from mcsplat.run import trained as trained_run
from mcsplat.cli import main

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"

LOUD = ["--steps", "3", "--model.num-init-points", "500", "--lpips-net", "alex", "--no-save-renders"]
TRAIN = LOUD + ["--quiet"]


def cut_scene(source: Path, root: Path, first: int, count: int) -> Path:
    """A copy of the blender scene `source` (the mini demo) with the demo's training frames first .. first + count - 1
    in place of its own (its test split kept)."""
    shutil.copytree(source, root, copy_function=shutil.copyfile)
    meta = json.loads((DEMO / "transforms_train.json").read_text())
    meta["frames"] = meta["frames"][first:first + count]
    for frame in meta["frames"]:
        name = Path(frame["file_path"]).name + ".png"
        shutil.copyfile(DEMO / "train" / name, root / "train" / name)
    (root / "transforms_train.json").write_text(json.dumps(meta))
    return root


@pytest.fixture(scope="module")
def trained(tmp_path_factory, mini_demo) -> tuple[Path, Path]:
    """(scene, run): a 3-step run of a copy of the mini demo, trained from the scene's parent folder with the scene
    given as a relative path."""
    root = tmp_path_factory.mktemp("resume_scene")
    scene = Path(shutil.copytree(mini_demo, root / "lego", copy_function=shutil.copyfile))
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(root)
        assert main(["train", "lego", "--out", "run"] + TRAIN) == 0
    return scene, root / "run"


@pytest.fixture
def run_copy(trained, tmp_path) -> Path:
    return Path(shutil.copytree(trained[1], tmp_path / "run"))


def files_of(run: Path) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in run.iterdir() if path.is_file()}


def test_config_json_names_the_scene_from_the_root_with_its_fingerprint(trained, tmp_path, monkeypatch):
    scene, run = trained
    config = json.loads((run / "config.json").read_text())
    assert config["data"] == str(scene), "stored as typed (lego), another folder's commands did not find it"
    assert config["scene"]["kind"] == "blender"
    assert (config["scene"]["train_views"], config["scene"]["test_views"]) == (12, 3)
    monkeypatch.chdir(tmp_path)
    assert len(trained_run.load(run, torch.device("cpu")).scene.train) == 12


def test_resume_refuses_another_scene_given_and_says_where_each_came_from(trained, run_copy, tmp_path, capsys):
    scene, _ = trained
    other = cut_scene(scene, tmp_path / "other", first=12, count=8)
    before = files_of(run_copy)
    assert main(["train", str(other), "--out", str(run_copy), "--resume"] + TRAIN) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and f"{other} (given on the command line) is not the scene" in error, error
    assert f"{scene} ({run_copy / 'config.json'} names it)" in error and "8 training and 3 test views" in error
    assert files_of(run_copy) == before, "nothing written"

    # config.json's path edited to the other scene: the scene named there is not the one the run trained on.
    config = json.loads((run_copy / "config.json").read_text())
    (run_copy / "config.json").write_text(json.dumps({**config, "data": str(other)}))
    assert main(["train", str(other), "--out", str(run_copy), "--resume"] + TRAIN) == 2
    error = capsys.readouterr().err
    assert f"--resume: {other} is not the scene this run trained on: it has 8 training" in error, error
    assert f"the path in {run_copy / 'config.json'} was edited" in error, error

    # Same counts, other views.
    same_counts = cut_scene(scene, tmp_path / "same_counts", first=12, count=12)
    assert main(["train", str(same_counts), "--out", str(run_copy), "--resume"] + TRAIN) == 2
    assert "other view names or image sizes" in capsys.readouterr().err


def test_resume_takes_the_scene_given_when_it_is_the_same_and_says_so(trained, run_copy, tmp_path, capsys):
    """The scene moved (config.json's path is gone), or config.json's path edited to another scene: the scene given
    is the one trained on, so the run goes on with it, saying so, and config.json names it from then on."""
    scene, _ = trained
    moved = Path(shutil.copytree(scene, tmp_path / "moved" / "lego", copy_function=shutil.copyfile))
    config = json.loads((run_copy / "config.json").read_text())
    (run_copy / "config.json").write_text(json.dumps({**config, "data": str(tmp_path / "gone")}))
    assert main(["train", str(moved), "--out", str(run_copy), "--resume"] + LOUD) == 0
    out = capsys.readouterr().out
    assert f"on the scene given, {moved} ({run_copy / 'config.json'} named {tmp_path / 'gone'}: the same views)" \
        in out, out
    saved = json.loads((run_copy / "config.json").read_text())
    assert saved["data"] == str(moved) and saved["scene"] == config["scene"]


def test_an_old_run_folder_without_a_fingerprint_still_resumes(trained, run_copy, tmp_path, capsys):
    scene, _ = trained
    config = json.loads((run_copy / "config.json").read_text())
    del config["scene"]
    (run_copy / "config.json").write_text(json.dumps(config))
    other = cut_scene(scene, tmp_path / "other", first=12, count=8)
    assert main(["train", str(other), "--out", str(run_copy), "--resume"] + TRAIN) == 2
    error = capsys.readouterr().err
    assert f"this run trained on {scene} ({run_copy / 'config.json'} names it), not on {other}" in error, error
    assert main(["train", str(scene), "--out", str(run_copy), "--resume"] + TRAIN) == 0
    assert json.loads((run_copy / "config.json").read_text())["scene"]["train_views"] == 12, "fingerprinted now"


def test_a_hand_edited_fingerprint_is_a_one_line_error(run_copy, trained, capsys):
    config = json.loads((run_copy / "config.json").read_text())
    (run_copy / "config.json").write_text(json.dumps({**config, "scene": {"kind": "blender"}}))
    assert main(["train", str(trained[0]), "--out", str(run_copy), "--resume"] + TRAIN) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "config.json: scene is" in error, error


def test_mask_and_depth_folders_are_named_from_the_root(tmp_path, monkeypatch, mini_demo):
    """--masks and --depths folders given from the current folder are kept from the root, as the scene is: `eval`
    or --resume run from elsewhere still finds them (their words, 'auto', 'none', 'alpha', stay words)."""
    from mcsplat.config import config_of

    monkeypatch.chdir(tmp_path)
    for masks, depths, expected in (("my-masks", "none", (str(tmp_path / "my-masks"), "none")),
                                    ("alpha", "sensor/depths", ("alpha", str(tmp_path / "sensor" / "depths")))):
        config = config_of(data=mini_demo, out=Path("run") / masks, masks=masks, depths=depths)
        lock = run_start.train_lock(config)
        try:
            begun = run_start.begin(config, lock)
        finally:
            lock.release()
        assert (begun.config.training_masks.masks, begun.config.depth_maps.depths) == expected and begun.plan is None


def test_a_run_begun_with_overwrite_resumes(mini_demo, tmp_path, capsys):
    """config.json keeps `overwrite: true` for a run begun with --overwrite; its --resume was refused with
    "--resume and --overwrite exclude each other", an option the command line had not given."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.json").write_text("{}")  # a folder that holds a run: --overwrite is needed
    assert main(["train", str(mini_demo), "--out", str(run), "--overwrite", "--save-every", "2"] + TRAIN) == 0
    assert json.loads((run / "config.json").read_text())["overwrite"] is True
    (run / "checkpoint.prev.pt").replace(run / "checkpoint.pt")  # as if stopped after step 2
    capsys.readouterr()
    assert main(["train", str(mini_demo), "--out", str(run), "--resume", "--quiet"]) == 0, capsys.readouterr().err
    assert trained_run.load(run, torch.device("cpu")).step == 3


def test_an_option_newer_than_the_checkpoint_is_compared_at_its_trained_value(run_copy, trained, capsys):
    """A checkpoint's copy of config.json written before an option existed (and before config.json had its plan)
    lacks it: the run trained with its value in config.json, and a --resume that gives another is refused, as for
    any other option."""
    from mcsplat.io.checkpoint import load_checkpoint, save_checkpoint
    from mcsplat.planning.config_file import settings_of

    state = load_checkpoint(run_copy / "checkpoint.pt")
    older = settings_of(state["config"])  # the layout before the plan: the plan's values in the options' places
    del state["version"], older["depth_correlation"]
    state["config"] = older
    save_checkpoint(run_copy / "checkpoint.pt", state)
    capsys.readouterr()
    assert main(["train", str(trained[0]), "--out", str(run_copy), "--resume", "--depth-correlation", "0.1"]) == 2
    assert "--depth-correlation 0.1 (trained with --depth-correlation 0.0)" in capsys.readouterr().err
