"""`train(config)`: a training run with its standard consumers, in one process or in each process of a torchrun
group. This is the Python API behind `mcsplat train`."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from .config import TrainConfig
from .distributed import Team, join
from .errors import MCSplatError
from .run.events import Control, Listener
from .run.folder import RunDir
from .run.start import folders_to_make, remove_if_empty, train_lock
from .subscribers import Checkpointer, ConsoleLog, LogWriter, MeshWriter, ProgressBar
from .trainer import TrainingRun


def standard_subscribers(config: TrainConfig, run_dir: Path) -> list[Listener]:
    """The consumers every run has (progress bar, console lines, log.jsonl, periodic checkpoints, the report), a
    --surface run's mesh, and the live viewer when asked for."""
    from .report import ReportWriter  # matplotlib: loaded only when training

    surface = config.surface_terms
    mesh = [MeshWriter(config.quiet)] if surface.surface and surface.surface_mesh else []  # the report pictures it
    subscribers = [ProgressBar(config.quiet), ConsoleLog(config.quiet), LogWriter(RunDir(run_dir).log_file),
                   Checkpointer(config.save_every, config.save_every_minutes), *mesh, ReportWriter()]
    viewer = config.live_viewer
    if viewer.viewer:
        from .viewer import TrainingViewer

        subscribers.append(TrainingViewer(host=viewer.host, port=viewer.port, quiet=config.quiet,
                                          origins=viewer.viewer_origin))
    return subscribers


def train(config: TrainConfig, subscribers: Sequence[Listener] = (), control: Control | None = None,
          team: Team | None = None) -> dict[str, Any]:
    """Run the whole job with the standard consumers plus `subscribers`; returns the final metrics. `team`: the
    processes that train this one model (default: torchrun's, or this process alone; a block's run is alone even
    under torchrun)."""
    if config.live_viewer.viewer:
        from .viewer import require_viser
        from .viewer.access import check_listen_address

        require_viser()  # before the run directory is made: a missing extra must not leave a half-started run
        check_listen_address(config.live_viewer.host, config.live_viewer.port)
    team = team or join(config.device, config.dist_timeout)
    lock = train_lock(config)
    made = folders_to_make(config.run_dir) if team.is_main else []
    finished = False
    try:
        if config.live_viewer.viewer and team.world_size > 1:
            raise MCSplatError("--viewer does not work with several training processes yet (pausing one would "
                               "stall the others); watch the run's checkpoints with `mcsplat view RUN` instead")
        run = TrainingRun(config, control, team, lock)
        # The other processes take part in each checkpoint (save_checkpoint), without writing anything.
        consumers = standard_subscribers(run.config, run.run_dir) + list(subscribers) if team.is_main else \
            [Checkpointer(run.config.save_every)]
        metrics = run.run(consumers)
        finished = True
        return metrics
    finally:
        lock.release()  # when the run could not start (it releases the lock itself once started)
        remove_if_empty(made)  # a run refused before it began leaves no folder behind
        team.close(finished)
