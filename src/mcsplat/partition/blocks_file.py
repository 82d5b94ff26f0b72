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
from typing import Any

from ..config import TrainConfig, from_jsonable, to_jsonable
from ..typed_json import describe, fits
from ..errors import MCSplatError
from ..io.atomic import atomic_write_text
from .cells import Cell
from .ground import GroundFrame
from .memory import estimated_bytes, format_bytes

VERSION = 1
NUMBER_LIST = re.compile(r"\[(?:\s*(?:-?[0-9][0-9.eE+-]*|null)\s*,?)+\s*\]")


class PlanError(MCSplatError):
    """blocks.json, or what it says of a block, cannot be trained as it is: only an edit of the plan (or a new plan)
    fixes it, not running `mcsplat blocks train` again."""


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
            raise PlanError(f"block {index} needs about {format_bytes(block.memory)} (cap {block.cap:,}, images of "
                            f"{block.pixels / 1e6:.1f} MP) but each block was given {format_bytes(self.memory_limit)}; "
                            f"lower its cap in the plan, or plan again with more blocks or more --memory")

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


# What each entry must be: a hand-edited `"cap": 1.7` or `"train_views": "1"` is refused, not coerced (to 1, ["1"]).
BOUNDS = tuple[float | None, float | None]
POINT = tuple[float, float, float]
PLAN_TYPES = {"scene": str, "margin": float, "min_view_share": float, "memory_limit": int | None, "total_cap": int,
              "ground": dict, "training": dict, "blocks": list}
GROUND_TYPES = {"first": POINT, "second": POINT, "up": POINT}
BLOCK_TYPES = {"index": int, "core": dict, "region": dict, "cap": int, "points": int, "pixels": int,
               "train_views": tuple[str, ...], "test_views": tuple[str, ...]}
CELL_TYPES = {"low": BOUNDS, "high": BOUNDS}
WORDS = {dict: "an object {...}", list: "a list", tuple[str, ...]: "a list of view names (strings)",
         BOUNDS: "a list of two numbers (or null)", POINT: "a list of three numbers"}


class HandEdited(ValueError):
    """A value of blocks.json that is there but not as the plan writes it (an edit by hand)."""


def read_plan(path: Path) -> BlockPlan:
    """The plan in `path`; one line naming what is wrong when it cannot be read (a PlanError)."""
    path = Path(path)
    if not path.is_file():
        raise PlanError(f"{path}: no block plan there; make one with `mcsplat blocks plan DATA --out "
                        f"{path.parent}`")
    try:
        data = json.loads(path.read_text())
        if not isinstance(data, dict) or data.get("version") != VERSION:
            version = data.get("version") if isinstance(data, dict) else None
            raise ValueError(f"version {version!r}, not {VERSION} (written by another mcsplat?)")
        _check_types(data, PLAN_TYPES, "")
        _check_types(data["ground"], GROUND_TYPES, "ground.")
        if not data["blocks"]:
            raise ValueError("it lists no blocks")
        blocks = tuple(_read_block(entry, position) for position, entry in enumerate(data["blocks"]))
        training = from_jsonable(data["training"], source="training")
        plan = BlockPlan(scene=Path(data["scene"]), ground=GroundFrame.from_json(data["ground"]),
                         margin=float(data["margin"]), min_view_share=float(data["min_view_share"]),
                         memory_limit=data["memory_limit"], total_cap=data["total_cap"], training=training,
                         blocks=blocks)
    except (MCSplatError, HandEdited) as error:
        raise PlanError(f"{path}: {error}") from None
    except (ValueError, KeyError, TypeError, AttributeError) as error:
        what = f"missing {error}" if isinstance(error, KeyError) else str(error)
        raise PlanError(f"{path}: not a block plan mcsplat can read ({what}); make it again with `mcsplat "
                        f"blocks plan`") from None
    return replace(plan, training=replace(plan.training, data=plan.scene))


def _check_types(entry: dict, types: dict[str, Any], where: str) -> None:
    """HandEdited naming the first of `types`' keys whose value in `entry` (`where` in the plan) is not of its
    type; KeyError for one that is missing."""
    if not isinstance(entry, dict):
        raise HandEdited(f"{where.rstrip('.') or 'the file'} is {json.dumps(entry)}; it must be an object {{...}}")
    for key, hint in types.items():
        value = entry[key]
        if not (isinstance(value, hint) if hint in (dict, list) else fits(value, hint)):
            raise HandEdited(f"{where}{key} is {json.dumps(value)}; it must be {WORDS.get(hint) or describe(hint)}")


def _read_block(entry: dict, position: int) -> Block:
    if not isinstance(entry, dict):
        raise HandEdited(f"block {position} is {json.dumps(entry)}; it must be an object {{...}}")
    _check_types(entry, BLOCK_TYPES, f"block {position}'s ")
    for cell in ("core", "region"):
        _check_types(entry[cell], CELL_TYPES, f"block {position}'s {cell}.")
    if entry["index"] != position:
        raise HandEdited(f"block {position} is numbered {entry['index']}: blocks are numbered 0, 1, 2... in order")
    if entry["cap"] < 1:
        raise HandEdited(f"block {position}'s cap is {entry['cap']}; give it at least 1")
    if not entry["train_views"]:
        raise HandEdited(f"block {position} has no training views; give it the views that see it")
    return Block(index=position, core=Cell.from_json(entry["core"]), region=Cell.from_json(entry["region"]),
                 cap=entry["cap"], points=entry["points"], pixels=entry["pixels"],
                 train_views=tuple(entry["train_views"]), test_views=tuple(entry["test_views"]))
