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
from ..events import Listener
from ..partition import BlockPlan, BlocksFolder, read_plan
from ..run_dir import RunDir
from ..train import train
from .merge import merge_blocks
from .workers import join_workers


def block_config(plan: BlockPlan, folder: BlocksFolder, index: int, **process: Any) -> TrainConfig:
    """The configuration of block `index`'s run: the plan's training options with the block's cap, folder and
    block, and this process's own options (`process`: device, threads, quiet); resumed when its folder holds a
    checkpoint, started again when it holds a run that never wrote one."""
    block = plan.block(index)
    run = RunDir(folder.block_run(index))
    resume = run.checkpoint_file.is_file()
    return dataclasses.replace(plan.training, out=run.path, cap_max=block.cap, block=folder.block_spec(index),
                               resume=resume, overwrite=run.holds_run() and not resume, named=None, **process)


def train_block(folder: BlocksFolder, index: int, subscribers: Sequence[Listener] = (), **process: Any
                ) -> dict[str, Any] | None:
    """Train block `index` to its end (its metrics), or None when it has been trained already. Refused before
    anything is written when its run does not fit the memory the plan gives each block."""
    plan = read_plan(folder.plan_file)
    plan.check_fits(index)
    run = RunDir(folder.block_run(index))
    quiet = process.get("quiet", False)
    if run.metrics_file.is_file():
        if not quiet:
            print(f"block {index}: trained already ({run.path})")
        return None
    config = block_config(plan, folder, index, **process)
    block = plan.block(index)
    if not quiet:
        how = "resumed" if config.resume else "training"
        print(f"block {index} of {len(plan.blocks)}: {how} in {run.path} ({len(block.train_views)} views, cap "
              f"{block.cap:,})")
    return train(config, subscribers, team=SingleProcess())


def train_blocks(folder: BlocksFolder, indices: Sequence[int] | None = None, device: str = "auto",
                 threads: int | None = None, quiet: bool = False) -> dict[str, Any] | None:
    """Train the blocks `indices` (default: all, then merge them); under torchrun each process its share. Returns
    the merged run's metrics (on rank 0, when all blocks were trained), else None."""
    plan = read_plan(folder.plan_file)
    chosen = list(range(len(plan.blocks))) if indices is None else list(indices)
    for index in chosen:
        plan.check_fits(index)  # every block refused before any starts
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
                failed = f"block {index}: {what}{error}"
                break
        failures = [failure for failure in workers.gather(failed) if failure]
        if not workers.is_main:
            if failed:
                raise MCSplatError(failed)
            return None
        if failures:
            raise MCSplatError("; ".join(failures) + f"; run `mcsplat blocks train {folder.path}` again to go on "
                               f"(trained blocks are kept, stopped ones resume)")
        return merge_blocks(folder, device=device, quiet=quiet) if indices is None else None
    finally:
        workers.close()
