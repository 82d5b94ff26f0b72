"""How a training run is asked to stop, or to write a checkpoint: Ctrl-C and SIGTERM (what `kill`, `timeout`, docker,
SLURM and Kubernetes send), and, with several processes, the requests agreed between them at each step."""

from __future__ import annotations

import signal

from .distributed import Team
from .events import Control
from .gaussians import GaussianModel


class StopSignals:
    """Within the block, a signal asks the run (its `control`) to stop at the end of the current step, which saves a
    checkpoint (a second signal stops at once). Once the last step's checkpoint is written (`stop_at_once`), a
    signal stops at once: --resume makes what the end of the run makes."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

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

    def reduce(self, model: GaussianModel, values: list[float]) -> list[float]:
        """The step's reduce (trainer.train_step): the values averaged, the requests voted."""
        control = self.control
        *averaged, stop, checkpoint = self.team.reduce_step(
            model, values + [float(control.stop_requested), float(control.checkpoint_requested)])
        self._stop, self._checkpoint = stop > 0, checkpoint > 0
        return averaged

    def stop(self) -> bool:
        return self.control.stop_requested if self.team.world_size == 1 else self._stop

    def checkpoint(self) -> bool:
        """A checkpoint asked for through Control (by time, see subscribers.Checkpointer)."""
        return self.control.checkpoint_requested if self.team.world_size == 1 else self._checkpoint
