"""The processes that share out the blocks: torchrun's (each rank trains every N-th block, and they meet once, at
the end, to tell rank 0 how their blocks went), or this process alone."""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from ..distributed.team import alone, join_torchrun

# A rank that has trained its blocks waits this long for the others (a block of a large scene trains for hours).
WAIT = timedelta(days=7)


@dataclass
class Workers:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def gather(self, value: Any) -> list[Any]:
        """Every process's `value`, in rank order (on every process)."""
        if self.world_size == 1:
            return [value]
        import torch.distributed as dist

        everyone: list[Any] = [None] * self.world_size
        dist.all_gather_object(everyone, value)
        return everyone

    def close(self) -> None:
        if self.owns_group:
            import torch.distributed as dist

            dist.destroy_process_group()


def join_workers() -> Workers:
    """torchrun's processes (gloo: the end-of-run message is a few bytes), the process group a script has made, or
    this process alone."""
    import torch.distributed as dist

    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if alone():
        return Workers()
    owns = not dist.is_initialized()
    if owns:
        join_torchrun("gloo", WAIT, "processes", "torchrun --nproc-per-node 2 -m mcsplat blocks train OUT")
    return Workers(dist.get_rank(), dist.get_world_size(), local_rank, owns)
