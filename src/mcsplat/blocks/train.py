"""`mcsplat blocks train`: each block trained as an ordinary run in its own folder (resume, signals, locks and
checkpoints as any run), alone even under torchrun; a block already trained is left as it is, one with a checkpoint
is resumed. Under torchrun each rank trains every N-th block, and rank 0 merges once all are trained."""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import torch

from ..compute.device import resolve_device
from ..config import TrainConfig
from ..distributed import SingleProcess, threads_per_process
from ..errors import MCSplatError
from ..run.events import Listener
from ..io.checkpoint import DamagedCheckpoint
from ..partition import BlockPlan, BlocksFolder, PlanError, read_plan
from ..partition.scene import block_views
from ..run.folder import RunDir
from ..run.scene import scene_of
from ..train import train
from .merge import merge_blocks
from .workers import join_workers


class BlockRefused(MCSplatError):
    """A block that running `mcsplat blocks train` again would not train until its folder is changed (the message
    says how)."""


# Failures that only a change fixes (the plan, a block's folder): no advice to run the command again after them.
NEEDS_A_CHANGE = (PlanError, BlockRefused)


def block_config(plan: BlockPlan, folder: BlocksFolder, index: int, **process: Any) -> TrainConfig:
    """The configuration of block `index`'s run: the plan's training options with the block's cap, folder and
    block, and this process's own options (`process`: device, threads, quiet); resumed when its folder holds a
    checkpoint, started again when it holds a run that never wrote one."""
    block = plan.block(index)
    run = RunDir(folder.block_run(index))
    resume = run.checkpoint_file.is_file()
    # A block's run makes no mesh of its part as it ends (--surface): `mcsplat export MERGED --format mesh` makes the
    # whole scene's.
    surface = dataclasses.replace(plan.training.surface_terms, surface_mesh=False)
    return dataclasses.replace(plan.training, out=run.path, cap_max=block.cap, block=folder.block_spec(index),
                               resume=resume, overwrite=run.holds_run() and not resume, named=None,
                               surface_terms=surface, **process)


def check_block(plan: BlockPlan, folder: BlocksFolder, index: int) -> None:
    """Refuse, before anything is written, a block whose run is estimated not to fit the memory the plan gives each
    block, and one whose run would resume with another cap than the plan's (a checkpoint continues with the cap it
    was trained to)."""
    plan.check_fits(index)
    run = RunDir(folder.block_run(index))
    if not run.checkpoint_file.is_file() or run.metrics_file.is_file():
        return
    cap, trained = plan.block(index).cap, run.read_config().cap_max
    if trained != cap:
        raise PlanError(f"{folder.plan_file}: block {index}'s cap is {cap:,}, but its run {run.path} was begun with "
                        f"cap {trained} and resumes with it; put {trained} back as its cap, or delete {run.path} to "
                        f"train the block from its start with the new cap")


def check_views(plan: BlockPlan, folder: BlocksFolder, indices: Sequence[int]) -> None:
    """Refuse, before any block starts, a block whose views the scene lacks, or that trains on a test view (each
    block's run checks its own again as it loads the scene)."""
    scene = scene_of(dataclasses.replace(plan.training, block=None))
    for index in indices:
        block_views(scene, plan.block(index), folder.plan_file)


def train_block(folder: BlocksFolder, index: int, subscribers: Sequence[Listener] = (), **process: Any
                ) -> dict[str, Any] | None:
    """Train block `index` to its end (its metrics), or None when it has been trained already. Refused before
    anything is written when its run does not fit the memory the plan gives each block, or would resume with
    another cap than the plan's."""
    plan = read_plan(folder.plan_file)
    check_block(plan, folder, index)
    run = RunDir(folder.block_run(index))
    block = plan.block(index)
    quiet = process.get("quiet", False)
    if run.metrics_file.is_file():
        if not quiet:
            print(f"block {index}: trained already ({run.path}){_trained_cap_note(run, block.cap)}")
        return None
    config = block_config(plan, folder, index, **process)
    if not quiet:
        how = "resumed" if config.resume else "training"
        print(f"block {index} of {len(plan.blocks)}: {how} in {run.path} ({len(block.train_views)} views, cap "
              f"{config.cap_max:,})")
    try:
        return train(config, subscribers, team=SingleProcess())
    except MCSplatError as error:
        damage = _damaged_checkpoint(error)
        if damage is None:
            raise
        raise BlockRefused(f"{damage}; {_damage_advice(run, folder, index)}") from None


def _trained_cap_note(run: RunDir, cap: int) -> str:
    """What a finished block's run was trained to, when the plan has since given it another cap."""
    trained = run.read_config().cap_max
    if trained == cap:
        return ""
    return f", with cap {trained}, not the plan's {cap:,}: delete {run.path} to train it with the plan's cap"


def _damaged_checkpoint(error: BaseException) -> DamagedCheckpoint | None:
    """The damaged checkpoint behind `error` (the run's own message advises --overwrite, which blocks do not take)."""
    while error is not None and not isinstance(error, DamagedCheckpoint):
        error = error.__cause__ or error.__context__
    return error


def _damage_advice(run: RunDir, folder: BlocksFolder, index: int) -> str:
    again = f"then run `mcsplat blocks train {folder.path}` again"
    if run.previous_checkpoint_file.is_file():
        return (f"go back to the checkpoint before it with `mv {run.previous_checkpoint_file} {run.checkpoint_file}`, "
                f"or delete {run.checkpoint_file} to train block {index} from its start; {again}")
    return (f"there is no older checkpoint to go back to: delete {run.checkpoint_file} to train block {index} from "
            f"its start; {again}")


def train_blocks(folder: BlocksFolder, indices: Sequence[int] | None = None, device: str = "auto",
                 threads: int | None = None, quiet: bool = False) -> dict[str, Any] | None:
    """Train the blocks `indices` (default: all, then merge them); under torchrun each process its share. Returns
    the merged run's metrics (on rank 0, when all blocks were trained), else None."""
    plan = read_plan(folder.plan_file)
    chosen = list(range(len(plan.blocks))) if indices is None else list(indices)
    for index in chosen:
        check_block(plan, folder, index)  # every block refused before any starts
    check_views(plan, folder, chosen)
    workers = join_workers()
    try:
        if workers.world_size > 1 and resolve_device(device).type == "cuda":
            torch.cuda.set_device(workers.local_rank % torch.cuda.device_count())
        if threads is None and workers.world_size > 1:
            threads = threads_per_process()  # the processes on this machine share its cores
        failed = None
        for index in chosen[workers.rank::workers.world_size]:
            try:
                train_block(folder, index, device=device, threads=threads, quiet=quiet)
            except Exception as error:  # a stop, or a block that cannot train: this rank trains no more
                # The others still hear of it (they would wait for this rank's word otherwise).
                what = "" if isinstance(error, MCSplatError) else f"{type(error).__name__}: "
                failed = (f"block {index}: {what}{error}", isinstance(error, NEEDS_A_CHANGE))
                break
        failures = [failure for failure in workers.gather(failed) if failure]
        if not workers.is_main:
            if failed:
                raise (BlockRefused if failed[1] else MCSplatError)(failed[0])
            return None
        if failures:
            raise blocks_failed(failures, folder)
        return merge_blocks(folder, device=device, quiet=quiet) if indices is None else None
    finally:
        workers.close()


def blocks_failed(failures: list[tuple[str, bool]], folder: BlocksFolder) -> MCSplatError:
    """One error for the blocks that failed ((message, whether only a change fixes it) each). Running the command
    again goes on after a stop; after a failure that needs a change of the plan or a block's folder, each message
    says what to change instead."""
    message = "; ".join(text for text, _ in failures)
    if any(needs_change for _, needs_change in failures):
        return BlockRefused(message)
    return MCSplatError(f"{message}; run `mcsplat blocks train {folder.path}` again to go on (trained blocks are "
                        f"kept, stopped ones resume)")
