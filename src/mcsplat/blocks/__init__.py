"""`mcsplat blocks`: a scene trained as independent blocks and merged into one model (docs/blocks.md).

- write_plan.py: `mcsplat blocks plan`, the plan made and written (partition/ makes it);
- train.py: a block trained as an ordinary run in its own folder; all blocks, or a process's share of them under
  torchrun (no gradient traffic: each rank trains whole blocks), then the merge;
- workers.py: the processes that share out the blocks (torchrun's, or this one);
- merge.py: each block's Gaussians inside its core cell, joined into one run folder and evaluated.
"""

from __future__ import annotations

from .merge import merge_blocks
from .write_plan import plan_blocks
from .train import block_config, train_block, train_blocks

__all__ = ["block_config", "merge_blocks", "plan_blocks", "train_block", "train_blocks"]
