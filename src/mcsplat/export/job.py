"""What a format's writer is handed: the run read back, the file to write and the options."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .options import ExportOptions

if TYPE_CHECKING:
    from ..run_dir import TrainedRun


@dataclass(frozen=True)
class ExportJob:
    run: TrainedRun
    path: Path
    options: ExportOptions

    def writing(self):
        """The run folder's lock while the file is written into it; a file elsewhere takes none (the run is only
        read)."""
        folder = self.run.folder
        return folder.lock("mcsplat export") if folder.contains(self.path) else contextlib.nullcontext()
