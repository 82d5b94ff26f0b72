"""What a training run tells its consumers, and the one interface through which they steer it (docs/architecture.md,
"The training loop as a stream of events").

The run (trainer.TrainingRun) emits, in this order:

    RunStarted
    KernelsCompiling (only on a machine whose kernel cache lacks some of the kernels)
    per step:  RefineDone (a step that relocated / grew / densified / pruned)
               EvalDone   (a periodic evaluation of the test views)
               StepDone   (always the last event of a step: its loss, PSNR, size, time)
               CheckpointWritten (whenever the checkpoint file was replaced)
    RunFinished (after the final evaluation and the exported .ply)

Consumers (the progress bar, the log.jsonl writer, the checkpointer, the report, the viewer) are Subscribers: any
callable taking an event. A Subscriber subclass gets `on_<kind>(event)` called for the kinds it defines. They run in
the training thread, between steps; anything slow (the viewer's rendering) belongs in its own thread. What they may
see of the run itself is RunView: the model, the scene, the configuration and the plan, and the two ways to act on it
(its Control, and writing a checkpoint now).
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Protocol, Sequence

import torch

from ..config import TrainConfig
from ..data import Scene
from .evaluation import Evaluation
from ..gaussians import GaussianModel
from ..metrics import StepValues, WithStepValues
from ..planning import Plan
from ..strategy.base import RefineReport


class RunView(Protocol):
    """The part of a training run its consumers may see (trainer.TrainingRun provides it)."""

    config: TrainConfig
    scene: Scene
    device: torch.device
    background: tuple[float, float, float]
    run_dir: Path
    control: "Control"

    @property
    def model(self) -> GaussianModel:
        """The model as it is now (read it between steps, or under control.lock from another thread)."""
        ...

    @property
    def plan(self) -> Plan:
        """The run's plan as it stands (its steps, schedules and cap; --budget plans again as it goes)."""
        ...

    @property
    def world_size(self) -> int:
        """How many processes train the model together (each step takes that many views)."""
        ...

    def save_checkpoint(self) -> None:
        """Write the checkpoint now (every process of a multi-process run must call it at the same step)."""
        ...


@dataclass(frozen=True)
class RunStarted:
    kind: ClassVar[str] = "run_started"
    run: RunView
    start_step: int
    init_note: str


@dataclass(frozen=True)
class KernelsCompiling:
    kind: ClassVar[str] = "kernels_compiling"
    modules: int  # Warp kernel modules not yet in the cache for this device: compiled now, once per machine


@dataclass(frozen=True)
class RefineDone:
    kind: ClassVar[str] = "refine_done"
    step: int  # the step index as the strategy saw it (counted from 0)
    report: RefineReport  # relocated / added / pruned (MCMC), cloned / split / pruned / reset (ADC)


@dataclass(frozen=True)
class EvalDone:
    kind: ClassVar[str] = "eval_done"
    step: int  # steps done
    psnr: float
    ssim: float
    num_gaussians: int


@dataclass(frozen=True)
class StepDone(WithStepValues):
    kind: ClassVar[str] = "step_done"
    step: int  # steps done (1 after the first step)
    total_steps: int
    values: StepValues  # the loss and train PSNR, on the step's device until read (a read waits for the step)
    num_gaussians: int
    sh_degree: int
    train_seconds: float  # training time so far, pauses and consumers not counted
    refine: RefineReport | None = None  # what the strategy did after this step's optimizer step
    resolution: float = 1.0  # the share of the image size the step trained at (coarse to fine)


@dataclass(frozen=True)
class CheckpointWritten:
    kind: ClassVar[str] = "checkpoint_written"
    step: int
    path: Path


@dataclass(frozen=True)
class RunFinished:
    kind: ClassVar[str] = "run_finished"
    run: RunView
    metrics: dict[str, Any]  # what metrics.json holds
    evaluation: Evaluation | None  # of the final model, per-view scores included; None: no test views


Event = RunStarted | KernelsCompiling | RefineDone | EvalDone | StepDone | CheckpointWritten | RunFinished
Listener = Callable[[Event], None]


class Subscriber:
    """Base for consumers: `on_step_done(event)` etc. are called for the events they define, the rest ignored."""

    def __call__(self, event) -> None:
        handler = getattr(self, f"on_{event.kind}", None)
        if handler is not None:
            handler(event)

    def close(self) -> None:
        """Called once when the run ends, normally or not (release threads, files, servers)."""


def close_all(listeners: Sequence[Listener]) -> None:
    """Close every listener that can be, even when one of them fails to (a viewer left open keeps its port and
    threads)."""
    for listener in listeners:
        close = getattr(listener, "close", None)
        if close is None:
            continue
        try:
            close()
        except Exception as error:
            warnings.warn(f"{type(listener).__name__} did not close cleanly: {error}", RuntimeWarning, stacklevel=2)


@dataclass
class Control:
    """Steering a run from outside its thread: pause / resume / stop, and the lock that the loop holds during a step
    so that a consumer can read the model consistently (the viewer renders under it, between steps)."""

    lock: threading.RLock = field(default_factory=threading.RLock)
    _running: threading.Event = field(default_factory=threading.Event)
    _stop: threading.Event = field(default_factory=threading.Event)
    _checkpoint: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        self._running.set()

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def stop(self) -> None:
        """Ask the loop to stop after the current step (it saves a checkpoint and says how to resume)."""
        self._stop.set()
        self._running.set()

    def request_checkpoint(self) -> None:
        """Ask the loop to write a checkpoint after a coming step (with several processes: the step after the
        request reaches the others with the gradients)."""
        self._checkpoint.set()

    def checkpoint_done(self) -> None:
        self._checkpoint.clear()

    @property
    def checkpoint_requested(self) -> bool:
        return self._checkpoint.is_set()

    @property
    def paused(self) -> bool:
        return not self._running.is_set()

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def wait_while_paused(self) -> None:
        while not self._running.wait(timeout=0.5):
            pass
