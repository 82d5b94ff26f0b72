"""A blocks folder: the only place its names are spelled.

    OUT/blocks.json    the plan (blocks_file.py)
    OUT/block_00/ ...  one ordinary run folder per block (resume, locks and checkpoints as any run)
    OUT/merged/        the merged model as a run folder: eval, render, export, view and report work on it
"""

from __future__ import annotations

from pathlib import Path

PLAN = "blocks.json"
MERGED = "merged"


class BlocksFolder:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.plan_file = self.path / PLAN
        self.merged = self.path / MERGED

    def block_run(self, index: int) -> Path:
        return self.path / f"block_{index:02d}"

    def block_runs(self) -> list[Path]:
        """The block run folders there are (trained or begun)."""
        return sorted(path for path in self.path.glob("block_[0-9]*") if path.is_dir())

    def block_spec(self, index: int) -> str:
        """How a block's run configuration names its block (scene.parse_block reads it): the plan's path from the
        block's run folder, so that the blocks folder may be moved."""
        return f"../{PLAN}#{index}"

    def __repr__(self) -> str:
        return f"BlocksFolder({str(self.path)!r})"
