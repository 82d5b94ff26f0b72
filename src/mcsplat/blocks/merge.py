"""`mcsplat blocks merge`: each block's live Gaussians inside its core cell (the margin's belong to a neighbour),
joined into one model and written as a run folder, OUT/merged/, that every command on runs reads (eval, render,
export, view, report): its config.json says the whole scene, its checkpoint holds the model (no optimiser state: it
is not resumed), its point_cloud.ply and metrics.json are the merged model's, scored on all the scene's test views."""

from __future__ import annotations

import dataclasses
from typing import Any

import torch

from ..run import folder as run_dir
from ..run import trained as trained_run
from ..compute.device import resolve_device
from ..errors import MCSplatError
from ..run.evaluation import evaluate
from ..gaussians import PARAM_KEYS, GaussianModel
from ..io.checkpoint import save_checkpoint
from ..io.lock import FolderLock
from ..partition import BlockPlan, BlocksFolder, read_plan
from ..planning import Plan
from ..run.metrics import metrics
from ..run.scene import background_of, scene_of


def kept_in_core(plan: BlockPlan, index: int, model: GaussianModel) -> torch.Tensor:
    """[N] bool: the block's Gaussians the merge keeps (alive, their centre in its core cell)."""
    where = plan.ground.coordinates(model.means.detach().cpu())
    return run_dir.alive(model).cpu() & plan.block(index).core.contains(where)


def joined(models: list[GaussianModel]) -> GaussianModel:
    """One model of all the Gaussians of `models`, in order (their SH degrees must agree)."""
    model = GaussianModel(*(torch.cat([part.params[key].detach() for part in models]) for key in PARAM_KEYS))
    model.antialiased = models[0].antialiased
    return model


def merge_blocks(folder: BlocksFolder, device: str = "auto", quiet: bool = False) -> dict[str, Any]:
    """Merge the trained blocks of `folder` into folder.merged; returns its metrics."""
    plan = read_plan(folder.plan_file)
    where = resolve_device(device)
    parts, counts, steps, block_plan = [], [], 0, None
    for block in plan.blocks:
        path = folder.block_run(block.index)
        if not run_dir.RunDir(path).metrics_file.is_file():
            raise MCSplatError(f"block {block.index} has not finished training ({path}); train it with `mcsplat "
                               f"blocks train {folder.path} --block {block.index}`")
        run = trained_run.load(path, where)
        keep = kept_in_core(plan, block.index, run.model)
        parts.append(run.model.subset(keep.to(where)))
        counts.append({"block": block.index, "gaussians": run.model.num_gaussians, "kept": int(keep.sum())})
        steps, block_plan = max(steps, run.step), block_plan or run.plan
    model = joined(parts)
    config = dataclasses.replace(plan.training, out=folder.merged, cap_max=plan.total_cap, block=None, named=None,
                                 resume=False, overwrite=False)
    merged_plan = _with_cap(block_plan, plan.total_cap)
    scene = scene_of(config)  # before anything is written: a scene that has moved writes nothing
    target = run_dir.RunDir(folder.merged)
    target.path.mkdir(parents=True, exist_ok=True)
    with FolderLock(target.lock_file, "mcsplat blocks merge").acquire():
        remove_previous_merge(target)
        target.write_config(config, merged_plan)
        save_checkpoint(target.checkpoint_file, {"model": model.state_dict(), "step": steps,
                                                 "merged_from": [str(folder.block_run(b.index)) for b in plan.blocks]})
        target.export_splats(model)
        record = {"num_gaussians": model.num_gaussians, "steps": steps, "blocks": counts}
        if scene.test:
            render_file = (lambda name: target.render_file("test", name)) if config.save_renders else None
            result = evaluate(model, scene.test, background_of(config, scene),
                              merged_plan.final_sh_degree(steps), where, lpips_net=config.lpips_net,
                              render_file=render_file, progress=not quiet)
            record = {**metrics(result, config.lpips_net, steps, model.num_gaussians), "blocks": counts}
        target.write_metrics(record)
    if not quiet:
        score = f"PSNR {record['psnr']:.3f} dB on {record['test_views']} test views, " if scene.test else ""
        print(f"merged {len(plan.blocks)} blocks: {score}{model.num_gaussians:,} Gaussians in {target.path}")
    return record


def remove_previous_merge(target: run_dir.RunDir) -> None:
    """An older merge's scores and Gaussians go before the new checkpoint lands: a merge stopped on the way leaves
    the new model without scores, never beside the old model's."""
    for old in (target.metrics_file, target.splats_file, target.previous_checkpoint_file):
        old.unlink(missing_ok=True)


def _with_cap(plan: Plan, cap: int) -> Plan:
    """The blocks' plan with the whole scene's cap (what the merged model was allowed in all)."""
    return dataclasses.replace(plan, schedule=dataclasses.replace(plan.schedule, cap_max=cap))
