"""A scene too large for one machine, cut into blocks that train as independent runs (docs/blocks.md).

- ground.py: the ground plane the blocks are cut on (from the cameras' up direction);
- cells.py: the cut itself, a k-d split of the scene's points into cells of equal weight;
- memory.py: what a block's run is estimated to hold, from its cap and its images;
- blocks_file.py: the plan (blocks.json): each block's cell, margin, views, cap and memory, and the training options;
- make.py: the plan made from a scene;
- scene.py: the scene a block's run trains on (its views and the points of its region);
- folder.py: the blocks folder (the plan, a run folder per block, the merged run).
"""

from __future__ import annotations

from .folder import BlocksFolder
from .make import make_plan
from .memory import estimated_bytes, format_bytes, parse_bytes
from .blocks_file import Block, BlockPlan, PlanError, read_plan
from .scene import block_scene

__all__ = ["Block", "BlockPlan", "BlocksFolder", "block_scene", "estimated_bytes", "format_bytes", "make_plan",
           "parse_bytes", "PlanError", "read_plan"]
