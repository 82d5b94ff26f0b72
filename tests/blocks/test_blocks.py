"""Blocks (`mcsplat blocks`): a real capture (the shared cup, at an eighth of its size) cut into blocks, each trained
as an ordinary run, and merged. The cut covers the scene; each block trains on its views and the points of its
region; a block that does not fit its memory is refused before it starts; a stopped block resumes exactly; the
merged model is the union of the blocks' own Gaussians and renders as that union does; blocks train one job each
(--block I) or as the processes of one torchrun group."""

from __future__ import annotations

import dataclasses
import json
import signal

import pytest
import torch

from mcsplat.blocks import block_config, plan_blocks, train_blocks
from mcsplat.blocks.merge import joined, kept_in_core
from mcsplat.cli import main
from mcsplat.config import ModelConfig, TrainConfig, config_of
from mcsplat.errors import MCSplatError
from mcsplat.partition import BlocksFolder, block_scene, estimated_bytes, read_plan
from mcsplat.partition.cells import split_cells
from mcsplat.partition.scene import OUTSIDE_SHARE
from mcsplat.render import render
from mcsplat.run.trained import load
from mcsplat.run.scene import scene_of
from mcsplat.strategy.mcmc import MCMCConfig
from tests.support.helpers import before_each_step, signal_at

STEPS = 120


def cup_training(shared_data, **overrides) -> TrainConfig:
    options = dict(data=shared_data / "colmap_cup", downscale=8, steps=STEPS, quiet=True, lpips_net="alex",
                   save_renders=False, save_every=60, threads=1, cap_max=8000, scale_schedule=False,
                   model=ModelConfig(sh_degree=1), mcmc=MCMCConfig(refine_start=30, refine_every=30))
    options.update(overrides)
    return config_of(**options)


def test_the_cells_cover_the_plane_once_and_share_the_points():
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(3000, 2, generator=generator, dtype=torch.float64) * torch.tensor([5.0, 1.0],
                                                                                           dtype=torch.float64)
    far = torch.tensor([[1e6, -1e6], [-1e9, 3.0], [0.0, 1e12]], dtype=torch.float64)
    for count in (1, 2, 3, 5, 8):
        cells = split_cells(points, count)
        members = torch.stack([cell.contains(torch.cat([points, far])) for cell in cells])
        assert (members.sum(dim=0) == 1).all(), f"{count} cells: a point in none or in two"
        shares = members[:, :len(points)].sum(dim=1)
        assert shares.max() - shares.min() <= count, f"{count} cells hold {shares.tolist()} points"
    first = split_cells(points, 2)[0]  # the long side (the first axis, 5x the spread) is cut first
    assert first.high[0] < float("inf") and first.high[1] == float("inf")


def test_a_plan_gives_each_block_its_views_points_and_share_of_the_cap(shared_data, tmp_path):
    training = cup_training(shared_data)
    plan = plan_blocks(training, tmp_path / "blocks", count=3)
    scene = scene_of(training)
    assert len(plan.blocks) == 3
    uv = plan.ground.coordinates(scene.points)
    cores = torch.stack([block.core.contains(uv) for block in plan.blocks])
    assert (cores.sum(dim=0) == 1).all(), "every SfM point belongs to exactly one block"
    for block in plan.blocks:
        in_region = block.region.contains(uv)
        assert in_region[cores[block.index]].all(), "a block's region holds its core"
        assert block.points == int(in_region.sum())
        assert block.cap == round(8000 * block.points / len(uv))
        assert block.memory == estimated_bytes(block.cap, 100 * 75)
        assert 10 <= len(block.train_views) <= len(scene.train) and block.test_views
    assert sum(block.cap for block in plan.blocks) > 8000, "the margins overlap: the blocks' caps add up to more"
    again = read_plan(BlocksFolder(tmp_path / "blocks").plan_file)
    assert again.to_json() == plan.to_json()

    # The scene of block 1's run: its views, the points of its region, and a thin sample of the others.
    folder = BlocksFolder(tmp_path / "blocks")
    part = block_scene(scene, folder.block_spec(1), folder.block_run(1))
    block = plan.blocks[1]
    assert [view.name for view in part.train] == list(block.train_views)
    assert [view.name for view in part.test] == list(block.test_views)
    inside = block.region.contains(plan.ground.coordinates(part.points))
    assert int(inside.sum()) == block.points
    assert 0 < int((~inside).sum()) <= OUTSIDE_SHARE * block.points

    with pytest.raises(MCSplatError, match="exists.*--overwrite"):
        plan_blocks(training, tmp_path / "blocks", count=2)


def test_memory_decides_the_blocks_and_a_block_that_does_not_fit_is_refused_before_it_starts(shared_data, tmp_path,
                                                                                             capsys):
    training = cup_training(shared_data, cap_max=400_000)
    one = estimated_bytes(400_000, 100 * 75)
    plan = plan_blocks(training, tmp_path / "fit", memory=int(one * 0.7))
    assert len(plan.blocks) > 1 and all(block.memory <= one * 0.7 for block in plan.blocks)
    with pytest.raises(MCSplatError, match=r"block \d of 2 needs about .* but --memory is"):
        plan_blocks(training, tmp_path / "tight", count=2, memory=estimated_bytes(1000, 7500))
    # A plan edited by hand: block 0's cap raised past what each block was given.
    folder = BlocksFolder(tmp_path / "fit")
    data = json.loads(folder.plan_file.read_text())
    data["blocks"][0]["cap"] = 10 * data["blocks"][0]["cap"]
    folder.plan_file.write_text(json.dumps(data))
    assert main(["blocks", "train", str(folder.path), "--quiet"]) == 2
    assert "block 0 needs about" in capsys.readouterr().err
    assert not folder.block_runs(), "refused before any block's run began"


def test_blocks_train_stop_resume_exactly_and_merge_into_one_run(shared_data, tmp_path, monkeypatch):
    training = cup_training(shared_data)
    straight, stopped = BlocksFolder(tmp_path / "straight"), BlocksFolder(tmp_path / "stopped")
    for folder in (straight, stopped):
        plan_blocks(training, folder.path, count=2)
    merged = train_blocks(straight, threads=1, quiet=True)

    with monkeypatch.context() as patch:
        before_each_step(patch, signal_at(70, signal.SIGINT))
        with pytest.raises(MCSplatError, match="block 0: stopped at step 71.*blocks train .* again"):
            train_blocks(stopped, threads=1, quiet=True)
    assert [path.name for path in stopped.block_runs()] == ["block_00"], "block 1 waits: it never began"
    assert block_config(read_plan(stopped.plan_file), stopped, 0).resume
    assert train_blocks(stopped, threads=1, quiet=True) == merged
    for folder in (straight, stopped):
        assert load(folder.block_run(0), torch.device("cpu")).step == STEPS
    for key, value in torch.load(straight.merged / "checkpoint.pt")["model"].items():
        assert torch.equal(torch.load(stopped.merged / "checkpoint.pt")["model"][key], value), key

    # The merged run is the union of each block's live Gaussians in its own cell, and renders as that union.
    plan = read_plan(straight.plan_file)
    parts = []
    for block in plan.blocks:
        model = load(straight.block_run(block.index), torch.device("cpu")).model
        parts.append(model.subset(kept_in_core(plan, block.index, model)))
    union = joined(parts)
    run = load(straight.merged, torch.device("cpu"))
    assert run.model.num_gaussians == union.num_gaussians == merged["num_gaussians"]
    assert [entry["kept"] for entry in merged["blocks"]] == [part.num_gaussians for part in parts]
    assert all(0 < part.num_gaussians for part in parts)
    where = plan.ground.coordinates(run.model.means.detach())
    owners = torch.stack([block.core.contains(where) for block in plan.blocks]).sum(dim=0)
    assert (owners == 1).all()
    view = run.scene.test[0]
    ours = render(run.model, view.camera, run.background, sh_degree=run.sh_degree).rgb
    theirs = render(union, view.camera, run.background, sh_degree=run.sh_degree).rgb
    assert torch.equal(ours, theirs)
    assert run.config.block is None and run.config.mcmc.cap_max == 8000
    assert len(run.scene.test) == merged["test_views"] == 10, "scored on every test view of the scene"
    with pytest.raises(MCSplatError, match="holds a model only"):
        from mcsplat.train import train

        train(dataclasses.replace(run.config, resume=True))


def test_one_job_per_block_then_merge_from_the_command_line(shared_data, tmp_path, capsys):
    out = tmp_path / "blocks"
    scene = str(shared_data / "colmap_cup")
    common = ["--downscale", "8", "--steps", "60", "--cap-max", "4000", "--threads", "1", "--lpips-net", "alex",
              "--no-save-renders", "--quiet"]
    with pytest.raises(SystemExit):  # the plan takes no --resume: `blocks train OUT` resumes what a stop left
        main(["blocks", "plan", scene, "--out", str(out), "--count", "2", "--resume", *common])
    assert not out.exists()
    assert main(["blocks", "plan", scene, "--out", str(out), "--count", "2", *common]) == 0
    with pytest.raises(SystemExit):  # the plan's options are the blocks': train takes the process options only
        main(["blocks", "train", str(out), "--steps", "10"])
    assert main(["blocks", "merge", str(out)]) == 2
    assert "block 0 has not finished training" in capsys.readouterr().err
    assert main(["blocks", "train", str(out), "--block", "1", "--quiet"]) == 0  # a job array's jobs: any order
    out = out.rename(tmp_path / "moved")  # a block's run finds its plan from where its folder is now
    assert main(["blocks", "train", str(out), "--block", "0", "--quiet"]) == 0
    assert not (out / "merged").exists(), "--block trains that block only"
    assert main(["eval", str(out / "block_01"), "--lpips-net", "alex"]) == 0
    assert main(["blocks", "train", str(out), "--block", "1"]) == 0
    assert "block 1: trained already" in capsys.readouterr().out
    assert main(["blocks", "merge", str(out)]) == 0
    metrics = json.loads((out / "merged" / "metrics.json").read_text())
    assert metrics["steps"] == 60 and metrics["num_gaussians"] == sum(entry["kept"] for entry in metrics["blocks"])
    assert main(["eval", str(out / "merged"), "--lpips-net", "alex"]) == 0
    assert main(["export", str(out / "merged"), "--format", "splat"]) == 0
    assert (out / "merged" / "point_cloud.splat").stat().st_size == 32 * metrics["num_gaussians"]


def test_the_processes_of_a_torchrun_group_share_the_blocks_and_rank_0_merges(shared_data, tmp_path):
    from tests.support.distributed_worker import train_blocks_run
    from tests.distributed.test_distributed import spawn

    folder = BlocksFolder(tmp_path / "blocks")
    plan_blocks(cup_training(shared_data, steps=60, save_every=0), folder.path, count=3)
    rank0, rank1 = spawn(tmp_path / "comm", 2, train_blocks_run, (str(folder.path),))
    assert rank0.get("trained") == [0, 2] and rank1.get("trained") == [1], (rank0, rank1)
    assert rank1["merged"] is None
    merged = rank0["merged"]
    assert merged["test_views"] == 10 and [entry["block"] for entry in merged["blocks"]] == [0, 1, 2]
    assert json.loads((folder.merged / "metrics.json").read_text()) == merged


def test_a_synthetic_scene_without_points_is_cut_where_its_cameras_stand(mini_demo, tmp_path):
    training = TrainConfig(data=mini_demo, steps=10, quiet=True, cap_max=1000)
    plan = plan_blocks(training, tmp_path / "blocks", count=2)
    scene = scene_of(training)
    for block in plan.blocks:
        standing = {view.name for view in scene.train
                    if block.region.contains(plan.ground.coordinates(view.camera.center[None]))[0]}
        assert set(block.train_views) == standing and len(standing) >= 1
        assert block.points == len(standing) and block.cap == round(1000 * len(standing) / len(scene.train))
    assert block_scene(scene, BlocksFolder(tmp_path / "blocks").block_spec(0),
                       BlocksFolder(tmp_path / "blocks").block_run(0)).points is None, "random init, as its run"


def test_a_block_run_with_surface_makes_no_mesh_of_its_part(shared_data, tmp_path):
    folder = BlocksFolder(tmp_path / "blocks")
    plan_blocks(cup_training(shared_data, surface=True), folder.path, count=2)
    surface = block_config(read_plan(folder.plan_file), folder, 0).surface_terms
    assert surface.surface and not surface.surface_mesh
