"""`mcsplat blocks` used carelessly (issue 58): a hand-edited blocks.json is read as written or refused in one line
(values of the wrong type, a test view among a block's training views, a cap changed under a checkpoint), the
options are checked before the scene loads, the messages point the way that fixes the problem, the help shows the
options the plan takes, and a merge stopped on the way never leaves a model beside another's scores.

The demo scene cut to 12 training views (`mini_demo`) in 2 blocks of a few steps each: seconds, not minutes."""

from __future__ import annotations

import json
import shutil

import pytest

from mcsplat import cli
from mcsplat.blocks import plan_blocks, train_block, train_blocks
from mcsplat.blocks.merge import merge_blocks
from mcsplat.blocks.train import BlockRefused, blocks_failed
from mcsplat.config import TrainConfig
from mcsplat.errors import MCSplatError
from mcsplat.partition import BlocksFolder, PlanError, read_plan
from mcsplat.run.folder import RunDir
from mcsplat.run.scene import scene_of

TRAINING = dict(steps=10, quiet=True, cap_max=1000, threads=1, lpips_net="alex", save_renders=False, save_every=0)


def mini_training(data, **overrides) -> TrainConfig:
    return TrainConfig(data=data, **{**TRAINING, **overrides})


@pytest.fixture(scope="module")
def trained(mini_demo, tmp_path_factory) -> BlocksFolder:
    """Two blocks of the mini demo trained and merged (copy it before changing it)."""
    folder = BlocksFolder(tmp_path_factory.mktemp("trained") / "blocks")
    plan_blocks(mini_training(mini_demo), folder.path, count=2)
    train_blocks(folder, threads=1, quiet=True)
    return folder


def copy_of(folder: BlocksFolder, tmp_path) -> BlocksFolder:
    return BlocksFolder(shutil.copytree(folder.path, tmp_path / "blocks"))


def edit_plan(folder: BlocksFolder, edit) -> None:
    data = json.loads(folder.plan_file.read_text())
    edit(data)
    folder.plan_file.write_text(json.dumps(data, indent=2))


def test_the_help_describes_blocks_and_shows_only_the_options_the_plan_takes(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    top = capsys.readouterr().out
    assert "Union" not in top and "A scene too large for one run, as blocks" in " ".join(top.split())
    with pytest.raises(SystemExit):
        cli.main(["blocks", "plan", "--help"])
    text = capsys.readouterr().out
    for refused in ("--resume", "--viewer", "--port", "--host", "--viewer-origin"):
        assert refused not in text, f"{refused} is listed, though blocks plan refuses it"
    assert "runs/<scene folder name>-blocks" in " ".join(text.replace("│", " ").split())
    assert "--count" in text and "--steps" in text, "its own options and those its blocks train with"
    with pytest.raises(SystemExit):
        cli.main(["blocks", "plan", "scene", "--resume"])


def test_the_options_are_checked_before_the_scene_loads(mini_demo, tmp_path, capsys):
    nowhere = tmp_path / "no-scene"  # a load would fail with "does not exist": the option's error comes first
    for options, message in ((["--cap-max", "1000"], "give the number of blocks (--count)"),
                             (["--cap-max", "1000", "--count", "0"], "--count must be between"),
                             (["--count", "2", "--cap-max", "auto"], "--cap-max auto grows one run"),
                             (["--cap-max", "1000", "--count", "2", "--margin", "-1"], "--margin must be")):
        assert cli.main(["blocks", "plan", str(nowhere), "--out", str(tmp_path / "out"), *options]) == 2
        error = capsys.readouterr().err
        assert "does not exist" not in error and message in error, error
    # train's refusal: every block's run would plan its steps by --budget and drop the --steps given
    out = tmp_path / "budget"
    common = ["blocks", "plan", str(mini_demo), "--out", str(out), "--count", "2", "--cap-max", "1000", "--quiet"]
    assert cli.main([*common, "--budget", "1m", "--steps", "20"]) == 2
    assert "--budget 1m plans the steps itself, so --steps 20 would be ignored" in capsys.readouterr().err
    assert not out.exists()
    assert cli.main([*common, "--budget", "1m"]) == 0
    assert read_plan(BlocksFolder(out).plan_file).training.budget == "1m"


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["blocks"][1].update(train_views="r_1"), "block 1's train_views is \"r_1\"; it must be a list"),
    (lambda d: d["blocks"][0].update(cap=1.7), "block 0's cap is 1.7; it must be a whole number"),
    (lambda d: d["blocks"][0].update(cap=True), "block 0's cap is true; it must be a whole number"),
    (lambda d: d["blocks"][0]["core"].update(low=["1", None]), "block 0's core.low is [\"1\", null]; it must be"),
    (lambda d: d.update(memory_limit="16G"), "memory_limit is \"16G\"; it must be a whole number or null"),
    (lambda d: d["ground"].update(up=[0, 1]), "ground.up is [0, 1]; it must be a list of three numbers"),
    (lambda d: d["training"].update(steps="20"), "blocks.json: training: steps is \"20\", not a whole number"),
], ids=["train_views", "cap", "cap-bool", "core", "memory_limit", "ground", "training"])
def test_values_of_the_wrong_type_are_refused_not_coerced(mini_demo, tmp_path, edit, message):
    folder = BlocksFolder(tmp_path / "blocks")
    plan_blocks(mini_training(mini_demo), folder.path, count=2)
    edit_plan(folder, edit)
    with pytest.raises(PlanError) as refused:
        read_plan(folder.plan_file)
    assert message in str(refused.value) and "config.json" not in str(refused.value)


def test_a_block_that_trains_on_a_test_view_or_names_an_unknown_one_is_refused_before_any_block_starts(
        mini_demo, tmp_path):
    scene = scene_of(mini_training(mini_demo))
    folder = BlocksFolder(tmp_path / "blocks")
    plan_blocks(mini_training(mini_demo), folder.path, count=2)
    edits = [(lambda d: d["blocks"][1]["train_views"].append(scene.test[0].name),
              f"block 1 trains on '{scene.test[0].name}', one of the scene's test views"),
             (lambda d: d["blocks"][1]["test_views"].append(scene.train[0].name),
              f"block 1 is scored on '{scene.train[0].name}', one of the scene's training views"),
             (lambda d: d["blocks"][1]["train_views"].append("train/nowhere"), "names the view 'train/nowhere'")]
    original = folder.plan_file.read_text()
    for edit, message in edits:
        folder.plan_file.write_text(original)
        edit_plan(folder, edit)
        with pytest.raises(PlanError, match=message) as refused:
            train_blocks(folder, threads=1, quiet=True)
        assert "again to go on" not in str(refused.value), "only an edit of the plan fixes it"
        assert not folder.block_runs(), "refused before block 0 began"


def test_a_cap_edited_under_a_checkpoint_is_refused_and_a_trained_block_says_its_own(trained, tmp_path, capsys):
    folder = copy_of(trained, tmp_path)
    run = RunDir(folder.block_run(0))
    run.metrics_file.unlink()  # stopped after its last checkpoint: the next `blocks train` resumes it
    checkpoint = run.checkpoint_file.read_bytes()
    cap = read_plan(folder.plan_file).block(0).cap
    edit_plan(folder, lambda d: d["blocks"][0].update(cap=cap // 2))
    with pytest.raises(PlanError, match=rf"block 0's cap is {cap // 2:,}, but its run .* was begun with cap {cap}"):
        train_blocks(folder, threads=1, quiet=True)
    assert run.checkpoint_file.read_bytes() == checkpoint and not run.metrics_file.exists()
    # A finished block is kept as it is, and says what it was trained with.
    run.metrics_file.write_text(RunDir(trained.block_run(0)).metrics_file.read_text())
    assert train_block(folder, 0, threads=1) is None
    assert f"trained already ({run.path}), with cap {cap}, not the plan's {cap // 2:,}" in capsys.readouterr().out


def test_a_damaged_block_checkpoint_says_what_blocks_train_can_do(trained, tmp_path):
    folder = copy_of(trained, tmp_path)
    run = RunDir(folder.block_run(0))
    run.metrics_file.unlink()
    damaged = bytearray(run.checkpoint_file.read_bytes())
    damaged[len(damaged) // 2] ^= 0xFF
    run.checkpoint_file.write_bytes(bytes(damaged))
    with pytest.raises(BlockRefused, match=rf"damaged checkpoint .* delete {run.checkpoint_file} to train block 0 "
                                           rf"from its start; then run `mcsplat blocks train") as refused:
        train_blocks(folder, [0], threads=1, quiet=True)
    assert "--overwrite" not in str(refused.value) and "again to go on" not in str(refused.value)


def test_only_a_stop_is_answered_with_running_blocks_train_again(tmp_path):
    folder = BlocksFolder(tmp_path / "blocks")
    stopped = blocks_failed([("block 0: stopped at step 5", False)], folder)
    assert "again to go on" in str(stopped) and not isinstance(stopped, BlockRefused)
    refused = blocks_failed([("block 0: stopped at step 5", False), ("block 1: names the view", True)], folder)
    assert isinstance(refused, MCSplatError) and "again to go on" not in str(refused)


def test_a_merge_stopped_on_the_way_leaves_no_scores_of_the_previous_merge(trained, tmp_path, monkeypatch):
    folder = copy_of(trained, tmp_path)
    merged = RunDir(folder.merged)
    assert merged.metrics_file.is_file()

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("mcsplat.blocks.merge.evaluate", stop)
    with pytest.raises(KeyboardInterrupt):
        merge_blocks(folder, quiet=True)
    assert merged.checkpoint_file.is_file() and merged.splats_file.is_file()
    assert not merged.metrics_file.exists(), "the new model beside the previous merge's scores"
