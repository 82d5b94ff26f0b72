"""`mcsplat blocks plan | train | merge`: a scene too large for one run, as blocks (docs/blocks.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Union

import tyro

from ..config import TrainConfig, ViewerOptions

from .trained import Device

BlocksFolder = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]


@dataclass(frozen=True)
class BlocksPlan(TrainConfig):
    """Cut a scene into blocks that train as independent runs and merge into one model (docs/blocks.md): blocks on
    the ground plane with equal shares of the SfM points, each with the views that see it and a share of --cap-max.
    Writes OUT/blocks.json (read it, edit it) and shows each block's views, cap and estimated memory. Takes every
    option of `mcsplat train`: each block trains with them."""

    out: Path | None = None
    """The blocks folder (default: runs/<scene folder name>-blocks)."""
    overwrite: bool = False
    """Plan again into a blocks folder that holds a plan (refused while it holds block runs trained to it)."""
    # What the plan refuses is hidden: `blocks train OUT` resumes the blocks a stop left, `view OUT/block_NN` shows one.
    resume: Annotated[bool, tyro.conf.Suppress] = False
    live_viewer: Annotated[ViewerOptions, tyro.conf.Suppress] = field(default_factory=ViewerOptions)
    count: int | None = None
    """Number of blocks (default: the fewest that fit --memory)."""
    memory: str | None = None
    """Memory each block's run may hold, e.g. 16GiB: blocks whose estimate exceeds it are refused before training."""
    margin: float = 0.2
    """Each block trains on the points of its cell grown by this share of its size on each side."""
    min_view_share: float = 0.25
    """A view trains a block when at least this share of the points it sees lie in the block's region."""

    def run_command(self) -> int:
        import dataclasses

        from ..blocks import plan_blocks
        from ..partition import parse_bytes

        training = TrainConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(TrainConfig)})
        out = self.out or Path("runs") / f"{Path(self.data).resolve().name}-blocks"
        plan_blocks(training, out, count=self.count, memory=None if self.memory is None else parse_bytes(self.memory),
                    margin=self.margin, min_view_share=self.min_view_share, overwrite=self.overwrite)
        return 0


@dataclass
class BlocksTrain:
    """Train the blocks of OUT/blocks.json, each as an ordinary run in OUT/block_NN/ (a trained block is kept, a
    stopped one resumes), then merge them into OUT/merged/. Under torchrun each process trains its share of the
    blocks and rank 0 merges; --block I trains one block only (one job of a job array), without merging."""

    out: BlocksFolder
    """Blocks folder written by `mcsplat blocks plan`."""
    block: int | None = None
    """Train this block only."""
    device: Device = "auto"
    threads: int | None = None
    """CPU threads of each block's run (default: all cores, shared between torchrun's processes)."""
    quiet: bool = False

    def run_command(self) -> int:
        from ..blocks import train_blocks
        from ..partition import BlocksFolder as Folder

        train_blocks(Folder(self.out), None if self.block is None else [self.block], device=self.device,
                     threads=self.threads, quiet=self.quiet)
        return 0


@dataclass
class BlocksMerge:
    """Merge the trained blocks of OUT into OUT/merged/: each block's Gaussians inside its own cell, one run folder
    that eval, render, export, view and report read, scored on all the scene's test views."""

    out: BlocksFolder
    """Blocks folder written by `mcsplat blocks plan`."""
    device: Device = "auto"
    quiet: bool = False

    def run_command(self) -> int:
        from ..blocks import merge_blocks
        from ..partition import BlocksFolder as Folder

        merge_blocks(Folder(self.out), device=self.device, quiet=self.quiet)
        return 0


Blocks = Union[Annotated[BlocksPlan, tyro.conf.subcommand("plan")],
               Annotated[BlocksTrain, tyro.conf.subcommand("train")],
               Annotated[BlocksMerge, tyro.conf.subcommand("merge")]]


def blocks(command: Annotated[Blocks, tyro.conf.OmitSubcommandPrefixes]) -> BlocksPlan | BlocksTrain | BlocksMerge:
    """A scene too large for one run, as blocks (docs/blocks.md): plan them (blocks.json), train each as a run of its
    own, merge them into one model."""
    return command  # a function rather than the Union itself: its docstring is the help of `mcsplat blocks`


