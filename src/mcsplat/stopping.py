"""How a command is asked to stop: Ctrl-C, SIGTERM (what `kill`, `timeout`, docker, SLURM and Kubernetes send) and
SIGHUP (a closed terminal). Every command stops as Ctrl-C stops it (`signals_interrupt`); a training run's steps stop
at the end of a step with a checkpoint, or write one when asked (with several processes, the requests agreed between
them at each step)."""

from __future__ import annotations

import contextlib
import signal
from typing import Iterator

import torch

from .distributed import Team
from .run.events import Control
from .gaussians import GaussianModel


# Ctrl-C raises KeyboardInterrupt already; these others end the process without a word unless handled.
TERMINATING = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextlib.contextmanager
def signals_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP raise KeyboardInterrupt as Ctrl-C does: the command stops with one line
    and its clean-up (a lock released, the folders a refused run made removed) runs, where the default would end the
    process on the spot. Every command runs in it (cli.main); a training run's steps answer the signals their own way
    (StopSignals)."""
    # Importing pycolmap installs glog's handler of SIGTERM, which prints a C++ stack and ends the process: imported
    # first, it is replaced by ours here instead of replacing ours when a loader imports it.
    import pycolmap  # noqa: F401

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = {}
    try:
        for number in TERMINATING:
            previous[number] = signal.signal(number, interrupt)
    except ValueError:  # not the main thread: the signals are not ours to handle
        pass
    try:
        yield
    finally:
        for number, handler in previous.items():
            if handler is not None:  # None: a handler set outside Python, which cannot be put back
                signal.signal(number, handler)


class StopSignals:
    """Within the block, a signal asks the run (its `control`) to stop at the end of the current step, which saves a
    checkpoint (a second signal stops at once). Once the last step's checkpoint is written (`stop_at_once`), a
    signal stops at once: --resume makes what the end of the run makes."""

    SIGNALS = (signal.SIGINT, *TERMINATING)

    def __init__(self, control: Control) -> None:
        self.control = control
        self.at_once = False
        self._previous: dict = {}

    def stop_at_once(self) -> None:
        """From now on a signal raises KeyboardInterrupt where the run is; so does one that came before."""
        self.at_once = True
        if self.control.stop_requested:
            raise KeyboardInterrupt

    def __enter__(self):
        def handler(signum, frame):
            if self.at_once or self.control.stop_requested:
                raise KeyboardInterrupt
            self.control.stop()
        try:
            for number in self.SIGNALS:
                self._previous[number] = signal.signal(number, handler)
        except ValueError:  # not the main thread: leave the signals alone
            pass
        return self

    def __exit__(self, *exc) -> None:
        for number, previous in self._previous.items():
            if previous is not None:  # None: a handler set outside Python, which cannot be put back
                signal.signal(number, previous)
        self._previous = {}


class AgreedRequests:
    """Control's stop and checkpoint requests as every process sees them. Alone, a request made during a step's
    events counts at once; together, only what every process agreed on in the step's all-reduce, where the requests
    travel with the gradients (or one would stop while the others wait for it)."""

    def __init__(self, control: Control, team: Team) -> None:
        self.control, self.team = control, team
        self._stop = self._checkpoint = False  # the votes of the last step's reduce

    def reduce(self, model: GaussianModel, values: torch.Tensor) -> torch.Tensor:
        """The step's reduce (step.Step): the values averaged, the requests voted. Alone, nothing to do: the values
        stay on the device unread."""
        if self.team.world_size == 1:
            return values
        control = self.control
        votes = torch.tensor([float(control.stop_requested), float(control.checkpoint_requested)],
                             dtype=values.dtype, device=values.device)
        averaged = self.team.reduce_step(model, torch.cat([values, votes]))  # on the host: the votes are read
        stop, checkpoint = averaged[-2:].tolist()
        self._stop, self._checkpoint = stop > 0, checkpoint > 0
        return averaged[:-2]

    def stop(self) -> bool:
        return self.control.stop_requested if self.team.world_size == 1 else self._stop

    def checkpoint(self) -> bool:
        """A checkpoint asked for through Control (by time, see subscribers.Checkpointer)."""
        return self.control.checkpoint_requested if self.team.world_size == 1 else self._checkpoint
