"""`mcsplat blocks plan`: the scene loaded as its runs will load it, cut into blocks, the plan written and shown."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ..config import TrainConfig, options_given
from ..errors import MCSplatError
from ..io.disk import writing_into
from ..partition import BlockPlan, BlocksFolder, make_plan
from ..partition.make import check_plan_options, plan_table
from ..run.scene import refuse_scene_folder
from ..run.scene import scene_of


def plan_blocks(training: TrainConfig, out: Path, count: int | None = None, memory: int | None = None,
                margin: float = 0.2, min_view_share: float = 0.25, overwrite: bool = False) -> BlockPlan:
    """Write OUT/blocks.json for `training` (the options every block trains with) and return the plan. The options
    are checked before the scene is loaded (a large one takes minutes)."""
    refuse_steps_beside_budget(training)
    check_plan_options(training, count, memory, margin, min_view_share)
    folder = BlocksFolder(out)
    refuse_scene_folder(folder.path, Path(training.data))
    if folder.plan_file.exists():
        if not overwrite:
            raise MCSplatError(f"{folder.plan_file} exists; train its blocks with `mcsplat blocks train "
                               f"{folder.path}`, or pass --overwrite to plan again")
        if folder.block_runs():  # trained to the old plan: they would be taken for blocks of the new one
            raise MCSplatError(f"{folder.path} holds block runs of its present plan ({folder.block_runs()[0].name}"
                               f"...); plan again into another --out")
    training = dataclasses.replace(training, out=None, resume=False, overwrite=False, block=None)
    scene = scene_of(training)
    plan = make_plan(scene, training, count=count, memory=memory, margin=margin, min_view_share=min_view_share)
    with writing_into(folder.path.parent):
        folder.path.mkdir(parents=True, exist_ok=True)
    plan.write(folder.plan_file)
    if not training.quiet:
        print(plan_table(plan))
        print(f"plan written to {folder.plan_file}; train with `mcsplat blocks train {folder.path}`")
    return plan


def refuse_steps_beside_budget(training: TrainConfig) -> None:
    """`mcsplat train`'s refusal, made when the plan is: every block's run would plan its steps by --budget and drop
    the --steps given, and the plan keeps no record of which options the command line named."""
    if training.budget is not None and "steps" in options_given(training):
        raise MCSplatError(f"--budget {training.budget} plans the steps itself, so --steps {training.steps} would be "
                           f"ignored by every block; give one of them")
