"""The plan of a partitioned scene, blocks.json: written before any block trains, read by every block's run and by
the merge, and meant to be read (and edited) by the user: which views each block trains on, its cap, its memory.

    {"version": 1, "scene": ..., "margin": 0.2, "min_view_share": 0.25, "memory_limit": null, "total_cap": ...,
     "ground": {"first": [...], "second": [...], "up": [...]},
     "training": {the options of `mcsplat train` every block trains with},
     "blocks": [{"index": 0, "core": {"low": [u, v], "high": [u, v]}, "region": {...}, "cap": ...,
                 "points": ..., "pixels": ..., "memory": ..., "train_views": [...], "test_views": [...]}, ...]}

A block owns the Gaussians of its core cell (the cores cover the ground plane without overlap); it trains on the
points of its region (the core grown by the margin) and the views that see it.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, replace
from pathlib import Path

from ..config import TrainConfig, from_jsonable, to_jsonable
from ..errors import MCSplatError
from ..io.atomic import atomic_write_text
from .cells import Cell
from .ground import GroundFrame
from .memory import estimated_bytes, format_bytes

VERSION = 1
NUMBER_LIST = re.compile(r"\[(?:\s*(?:-?[0-9][0-9.eE+-]*|null)\s*,?)+\s*\]")


@dataclass(frozen=True)
class Block:
    index: int
    core: Cell                      # the Gaussians it keeps in the merge
    region: Cell                    # the points it trains from: the core and its margin
    cap: int                        # the most Gaussians its run holds
    points: int                     # the scene's points in its region
    pixels: int                     # the largest of its training images
    train_views: tuple[str, ...]
    test_views: tuple[str, ...]

    @property
    def memory(self) -> int:
        """Estimated peak bytes of its run."""
        return estimated_bytes(self.cap, self.pixels)


@dataclass(frozen=True)
class BlockPlan:
    scene: Path
    ground: GroundFrame
    margin: float
    min_view_share: float
    memory_limit: int | None        # bytes each block's run may hold (--memory), or None
    total_cap: int                  # the Gaussians of the merged model, about (the sum of the cores' shares)
    training: TrainConfig           # what every block trains with (its cap, folder and block set per block)
    blocks: tuple[Block, ...]

    def block(self, index: int) -> Block:
        if not 0 <= index < len(self.blocks):
            raise MCSplatError(f"block {index} does not exist: the plan has blocks 0 to {len(self.blocks) - 1}")
        return self.blocks[index]

    def check_fits(self, index: int) -> None:
        """A one-line error when the block's run is estimated to need more memory than it was given."""
        block = self.block(index)
        if self.memory_limit is not None and block.memory > self.memory_limit:
            raise MCSplatError(f"block {index} needs about {format_bytes(block.memory)} (cap {block.cap:,}, images of "
                               f"{block.pixels / 1e6:.1f} MP) but each block was given {format_bytes(self.memory_limit)}"
                               f"; lower its cap in the plan, or plan again with more blocks or more --memory")

    def to_json(self) -> dict:
        training = to_jsonable(self.training)
        return {"version": VERSION, "scene": str(self.scene), "margin": self.margin,
                "min_view_share": self.min_view_share, "memory_limit": self.memory_limit,
                "total_cap": self.total_cap, "ground": self.ground.to_json(), "training": training,
                "blocks": [_block_json(block) for block in self.blocks]}

    def write(self, path: Path) -> None:
        # Lists of numbers (a bound, an axis) on one line, so that the file reads as a table.
        text = NUMBER_LIST.sub(lambda match: json.dumps(json.loads(match.group(0))),
                               json.dumps(self.to_json(), indent=2))
        atomic_write_text(path, text + "\n")


def _block_json(block: Block) -> dict:
    return {"index": block.index, "core": block.core.to_json(), "region": block.region.to_json(), "cap": block.cap,
            "points": block.points, "pixels": block.pixels, "memory": block.memory,
            "train_views": list(block.train_views), "test_views": list(block.test_views)}


def read_plan(path: Path) -> BlockPlan:
    """The plan in `path`; one line naming what is wrong when it cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise MCSplatError(f"{path}: no block plan there; make one with `mcsplat blocks plan DATA --out "
                           f"{path.parent}`")
    try:
        data = json.loads(path.read_text())
        if data.get("version") != VERSION:
            raise ValueError(f"version {data.get('version')!r}, not {VERSION} (written by another mcsplat?)")
        blocks = tuple(_read_block(entry, position) for position, entry in enumerate(data["blocks"]))
        if not blocks:
            raise ValueError("it lists no blocks")
        training = from_jsonable(data["training"])
        plan = BlockPlan(scene=Path(data["scene"]), ground=GroundFrame.from_json(data["ground"]),
                         margin=float(data["margin"]), min_view_share=float(data["min_view_share"]),
                         memory_limit=None if data["memory_limit"] is None else int(data["memory_limit"]),
                         total_cap=int(data["total_cap"]), training=training, blocks=blocks)
    except MCSplatError as error:
        raise MCSplatError(f"{path}: {error}") from None
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        what = f"missing {error}" if isinstance(error, KeyError) else str(error)
        raise MCSplatError(f"{path}: not a block plan mcsplat can read ({what}); make it again with `mcsplat "
                           f"blocks plan`") from None
    return replace(plan, training=replace(plan.training, data=plan.scene))


def _read_block(entry: dict, position: int) -> Block:
    if entry["index"] != position:
        raise ValueError(f"block {position} is numbered {entry['index']}: blocks are numbered 0, 1, 2... in order")
    cap = int(entry["cap"])
    if cap < 1:
        raise ValueError(f"block {position}'s cap is {cap}; give it at least 1")
    train = tuple(str(name) for name in entry["train_views"])
    if not train:
        raise ValueError(f"block {position} has no training views")
    return Block(index=position, core=Cell.from_json(entry["core"]), region=Cell.from_json(entry["region"]),
                 cap=cap, points=int(entry["points"]), pixels=int(entry["pixels"]), train_views=train,
                 test_views=tuple(str(name) for name in entry["test_views"]))
