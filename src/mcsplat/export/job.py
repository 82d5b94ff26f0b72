"""What a format's writer is handed: the run read back, the file to write and the options that writers read."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..mesh.options import MeshOptions
from .selection import SelectionOptions

if TYPE_CHECKING:
    from ..run.trained import TrainedRun


@dataclass(frozen=True)
class ExportJob:
    run: TrainedRun
    path: Path
    selection: SelectionOptions  # a Gaussian format's
    mesh: MeshOptions  # the mesh's
    spz_version: int
    device: str  # where the run's report is made again (the mesh)

    def writing(self):
        """The run folder's lock while the file is written into it; a file elsewhere takes none (the run is only
        read)."""
        folder = self.run.folder
        return folder.lock("mcsplat export") if folder.contains(self.path) else contextlib.nullcontext()
