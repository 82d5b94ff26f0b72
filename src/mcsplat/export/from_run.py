"""`mcsplat export` without its parsing: a trained run's folder to the file of one format of the table."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import MCSplatError
from .job import ExportJob
from .options import ExportOptions
from .target import export_target
from .unread import refuse_unread_options

if TYPE_CHECKING:
    from ..run.trained import TrainedRun


def export_run(path: str | Path, options: ExportOptions = ExportOptions()) -> Path:
    """Write the run in `path` as `options` say; returns the file written. Every refusal is one MCSplatError, and
    nothing is written before the checks that can refuse have passed."""
    from ..compute.device import resolve_device
    from ..run.folder import RunDir
    from ..run.trained import load

    folder = RunDir(path)
    folder.read_config()  # a run folder, or the one-line error, before any work
    chosen, target = export_target(folder, options.format, options.out)
    refuse_unread_options(chosen, options)
    run = load(path, resolve_device(options.device))
    _refuse_non_finite(run)  # one check for every format, the mesh's included
    chosen.write(ExportJob(run, target, options.selection, options.mesh, options.spz_version, options.device))
    return target


def _refuse_non_finite(run: TrainedRun) -> None:
    """A one-line error when the model holds NaN or infinite parameters (a diverged run): no format is written."""
    import torch

    broken = [name for name, value in run.model.params.items() if not torch.isfinite(value.detach()).all()]
    if broken:
        raise MCSplatError(f"{run.folder.checkpoint_file}: NaN or infinite values in {', '.join(broken)}, so nothing "
                           f"is exported; the run diverged: train it again, or go back to "
                           f"{run.folder.previous_checkpoint_file.name}")
