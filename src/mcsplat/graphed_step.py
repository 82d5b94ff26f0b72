"""A training step replayed as a CUDA graph (--cuda-graph): `GraphedStep(step)` takes the place of step.py's `Step`.

On a GPU most of a small step is the host's work: Python, and about 170 launches, each waited for. A CUDA graph
records the step's launches once (a capture) and replays them all with one call. A replay repeats the capture's
kernels with the capture's arguments, so:

- **Inputs in fixed places.** Before each replay the view's camera is copied into a camera slot
  (render/project/camera_slot.py), its photo and mask into buffers of the capture. The position learning rate and
  the noise's rate are tensors on the device (optim.rates_on_device; `noise_lr` here), written before the replay.
  The pair lists go into a room of a size fixed ahead (render/bin/pair_room.py).
- **Nothing read back inside.** tests/training/test_device_reads.py holds the step to that.
- **The same Python branches.** A graph serves one *phase* of the run, and a step in another phase is not replayed.
  The phase holds the image size, the SH degree, whether the view has a mask, the number of Gaussians, the memory of
  their parameters and Adam state (row surgery replaces it), the size of the pairs' room, the strategy's graph_phase
  and each loss term's.
  - A step whose strategy or terms say None runs as it is: refine steps (row surgery, counts read), ADC, the depth
    and --surface terms.
  - A step in a new phase runs as it is WARM_STEPS times (or more: a warm step may itself change the phase, as the
    first after growth makes the strategy's statistics for the new count), so that nothing is done for the first
    time inside a capture (Adam's state, the room of a new size, kernels loaded). Then it is captured, and the graph
    is run once. Only the last graph is kept, and at most CAPTURES_PER_WINDOW are made in any WINDOW steps: while the
    phase keeps changing (coarse to fine, views of several sizes) the steps run as they are.
- **What a graph cannot hold runs as before:** per-image modules (--pose-opt, --appearance), several processes, the
  CPU's fused update, ADC, MCMC's noise on every parameter, and a noise of rate 0.

The graph's memory is its own (torch's graph pool): a run on a GPU keeps the step's intermediate buffers twice, once
for the graph and once for the steps that run as they are.

The CPU has no graphs. Its tests stand a recorder in for one (tests/support/graph_check.py): it runs the captured work
again at each replay, and checks that the work launches the same kernels, operators and sorts with the same numbers,
and reads everything made before the step from the same memory.
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Protocol

import torch

from .data import View
from .gaussians import PARAM_KEYS
from .loss_terms import graph_phase as terms_phase
from .metrics import StepValues
from .optim import PlainUpdate, rates_on_device
from .planning import Plan
from .render.bin import pair_room
from .render.constants import TILE_SIZE
from .render.project.camera_slot import CameraSlot
from .render.project.warp_kernel import fill_slot
from .step import Step, StepInputs, StepResult, alone
from .strategy.base import RefineReport, graph_phase as strategy_phase

WARM_STEPS = 2  # steps a new phase runs as it is before its capture
# At most this many captures in any WINDOW steps: each capture waits for the GPU and collects garbage, more than a few
# replays save, so while the phase keeps changing (coarse to fine, views of several sizes) the steps run as they are.
CAPTURES_PER_WINDOW, WINDOW = 4, 64


class CaptureFailed(RuntimeError):
    """The device could not capture the step (the run goes on without a graph)."""


class GraphBackend(Protocol):
    def settle(self) -> None:
        """Wait for the device's queue (before a capture: what the host reads of earlier steps has arrived)."""
        ...

    def capture(self, work: Callable[[], Any]) -> None:
        """Record `work` as the graph, in place of the one before, and leave it done once; CaptureFailed, with
        nothing done, when the device cannot."""
        ...

    def replay(self) -> None:
        ...


class CudaGraphs:
    """torch's CUDA graphs, holding Warp's launches and sorts too: they run on torch's current stream (compute/
    runtime.py), and Warp is told of the capture, so that its sort's scratch memory is the graph's."""

    def __init__(self, device: torch.device, generators: tuple[torch.Generator, ...] = ()):
        self.device, self.generators = device, generators
        self._graph: torch.cuda.CUDAGraph | None = None
        self._warp_graph: Any = None  # Warp's record of the capture: it frees the sort's scratch memory when dropped
        self._pool = torch.cuda.graph_pool_handle()  # every capture of the run shares one pool

    def settle(self) -> None:
        torch.cuda.synchronize(self.device)

    def capture(self, work: Callable[[], Any]) -> None:
        import warp as wp

        from .compute.runtime import warp_stream

        self._graph = self._warp_graph = None  # the old graph's memory goes back to the pool first
        graph = torch.cuda.CUDAGraph()
        try:
            for generator in self.generators:  # the noise's generator advances at each replay
                graph.register_generator_state(generator)
            # thread_local: the threads decoding the next views may pin memory while this one captures
            with torch.cuda.graph(graph, pool=self._pool, capture_error_mode="thread_local"):
                stream = warp_stream(self.device)
                wp.capture_begin(stream=stream, external=True)
                try:
                    work()
                finally:
                    warp_graph = wp.capture_end(stream=stream)
        except Exception as error:  # nothing ran: a capture records without running
            raise CaptureFailed(f"{type(error).__name__}: {error}") from error
        self._graph, self._warp_graph = graph, warp_graph
        graph.replay()

    def replay(self) -> None:
        self._graph.replay()


@dataclass
class _Captured:
    """A graph's phase, the fixed places of its inputs, and what its capture returned."""

    phase: tuple
    inputs: StepInputs
    slot: CameraSlot
    values: torch.Tensor  # [loss, PSNR], written by each replay
    refine: RefineReport | None = None  # the strategy's report of the capture's step, the same at each replay
    room: pair_room.PairRoom | None = None  # the pairs' room its render writes the count of (kept while it lives)


def _tiles(camera: Any) -> tuple[int, int]:
    return -(-camera.width // TILE_SIZE), -(-camera.height // TILE_SIZE)


class GraphedStep:
    """`step` (step.Step), each step replayed from a CUDA graph where its phase allows (the module's docstring);
    `backend` records and replays (CudaGraphs on a GPU; the tests' recorder on the CPU). `captures`, `replays` and
    `as_they_are` count the steps each way went."""

    def __init__(self, step: Step, backend: GraphBackend | None = None):
        self.step = step
        generator = getattr(step.strategy, "generator", None)
        self.backend = backend or CudaGraphs(step.device, (generator,) if generator is not None else ())
        rates_on_device(step.optimizers)
        # the noise's rate, a double as the number was (on the CPU the same noise to the bit)
        self.noise_lr = torch.zeros((), dtype=torch.float64, device=step.device)
        self.captures = self.replays = self.as_they_are = 0
        self.failed = False  # a capture failed: every step runs as it is
        self._captured: _Captured | None = None
        self._warming: tuple | None = None  # the phase being warmed,
        self._slot: CameraSlot | None = None  # the slot its capture will read the camera from (it notes the size)
        self._warm = 0  # and its steps so far
        self._recent: deque[bool] = deque(maxlen=WINDOW)  # whether each of the last steps was a capture

    # what the run and its planner use of a step (planning/planner.py's RunStep)
    @property
    def device(self) -> torch.device:
        return self.step.device

    @property
    def background(self) -> Any:
        return self.step.background

    def on(self, model: Any, optimizers: dict, strategy: Any) -> Step:
        return self.step.on(model, optimizers, strategy)

    def check_finite(self) -> None:
        self.step.check_finite()

    def __call__(self, step: int, view: View, plan: Plan, view_index: int = 0) -> StepResult:
        captures = self.captures
        done = self._step(step, view, plan, view_index)
        self._recent.append(self.captures > captures)
        return done

    def _step(self, step: int, view: View, plan: Plan, view_index: int) -> StepResult:
        inputs = self.step.inputs(step, view, plan, view_index)
        phase = self.phase(step, plan, inputs) if not self.failed else None
        if phase is None:
            return self._as_it_is(step, view, plan, view_index, inputs, None)
        captured = self._captured
        if captured is not None and captured.phase == phase:
            return self._replay(step, plan, inputs, captured)
        if self._warming == phase and self._warm >= WARM_STEPS and sum(self._recent) < CAPTURES_PER_WINDOW:
            self.backend.settle()
            settled = self.phase(step, plan, inputs)  # with every count of the steps before at hand
            if settled == phase:
                return self._capture(step, view, plan, view_index, inputs, phase)
            phase = settled  # the pairs' room follows a count that arrived: warm that phase
        if phase is None:
            return self._as_it_is(step, view, plan, view_index, inputs, None)
        if self._warming != phase:
            self._warming, self._warm = phase, 0
            self._slot = CameraSlot(self.step.model.means.dtype, self.step.device)
        self._warm += 1
        return self._as_it_is(step, view, plan, view_index, inputs, self._slot)

    def phase(self, step: int, plan: Plan, inputs: StepInputs) -> tuple | None:
        """What the step's work branches on (the module's docstring); None: the step cannot be replayed."""
        s = self.step
        if s.modules or s.reduce is not alone or type(s.update) is not PlainUpdate or s.phases is not None:
            return None
        strategy, terms = strategy_phase(s.strategy, step), terms_phase(s.terms(), step, plan.steps)
        if strategy is None or terms is None:
            return None
        if s.noise_lr(step, plan) == 0:  # the step skips a noise of rate 0, which a graph would draw
            return None
        camera, model = inputs.camera, s.model
        room = pair_room.room_at(model.means.device, *_tiles(camera))
        room_phase = (id(room), room.size(model.num_gaussians)) if room is not None else None
        return (camera.width, camera.height, inputs.keep is not None, plan.sh_degree_at(step), model.num_gaussians,
                room_phase, _memory_of(s), strategy, terms)

    def _as_it_is(self, step: int, view: View, plan: Plan, view_index: int, inputs: StepInputs,
                  slot: CameraSlot | None) -> StepResult:
        self.as_they_are += 1
        if slot is None:
            return self.step.run(step, view, plan, view_index, inputs)
        with slot.serving():  # an empty slot: it notes the render's settings
            return self.step.run(step, view, plan, view_index, inputs)

    def _capture(self, step: int, view: View, plan: Plan, view_index: int, inputs: StepInputs,
                 phase: tuple) -> StepResult:
        s, slot = self.step, self._slot
        fixed = StepInputs(inputs.camera, torch.empty_like(inputs.target),
                           None if inputs.keep is None else torch.empty_like(inputs.keep))
        captured = _Captured(phase, fixed, slot, torch.empty(2, dtype=s.model.means.dtype, device=s.device))
        self._captured = None
        self._load(step, plan, inputs, captured)
        returned: dict[str, Any] = {}

        def work() -> None:
            with slot.serving():
                values, returned["refine"] = s.work(step, view, plan, view_index, fixed, self.noise_lr)
            captured.values.copy_(values)  # into a place of its own, which each replay writes

        try:
            self.backend.capture(work)
        except CaptureFailed as error:
            warnings.warn(f"the training step could not be captured as a CUDA graph ({error}); the run goes on "
                          f"without one", RuntimeWarning, stacklevel=3)
            self.failed = True
            for param in s.model.params.values():  # the capture's backward may have left gradients: none ran
                param.grad = None
            return self._as_it_is(step, view, plan, view_index, inputs, None)
        captured.refine = returned["refine"]
        captured.room = pair_room.room_at(s.model.means.device, *_tiles(fixed.camera))
        self._captured, self._warming = captured, None
        self.captures += 1
        return self._done(step, captured)

    def _replay(self, step: int, plan: Plan, inputs: StepInputs, captured: _Captured) -> StepResult:
        self._load(step, plan, inputs, captured)
        self.backend.replay()
        self.replays += 1
        return self._done(step, captured)

    def _load(self, step: int, plan: Plan, inputs: StepInputs, captured: _Captured) -> None:
        """The step's numbers and its view into the graph's fixed places: copies on the device."""
        s = self.step
        s.set_rates(step, plan)
        self.noise_lr.fill_(s.noise_lr(step, plan))
        fill_slot(captured.slot, inputs.camera)
        captured.inputs.target.copy_(inputs.target)
        if inputs.keep is not None:
            captured.inputs.keep.copy_(inputs.keep)

    def _done(self, step: int, captured: _Captured) -> StepResult:
        if captured.room is not None:
            captured.room.replayed()
        values = captured.values.clone()  # the graph writes its own at the next replay
        self.step.finite.add(step, values)
        return StepResult(StepValues(values), captured.refine)


def _memory_of(step: Step) -> tuple[int, ...]:
    """Where the model's parameters and their Adam state live: row surgery that adds or removes Gaussians replaces
    them, and a graph reads them where its capture found them."""
    places = []
    for key in PARAM_KEYS:
        param = step.model.params[key]
        places.append(param.data_ptr())
        state = step.optimizers[key].state.get(param, {})
        places.extend(value.data_ptr() for _, value in sorted(state.items()) if isinstance(value, torch.Tensor))
    return tuple(places)


def not_replayable(step: Step) -> str | None:
    """Why none of the run's steps can be replayed as a graph, or None."""
    if step.device.type != "cuda":
        return "on the CPU"
    if step.modules:
        return "with per-image modules (--pose-opt, --appearance)"
    if step.reduce is not alone:
        return "with several processes"
    if type(step.update) is not PlainUpdate:
        return "with the fused update"
    if getattr(step.strategy, "graph_phase", None) is None:
        return "with this strategy (ADC)"
    return None


def graphed(step: Step, asked: bool) -> Step | GraphedStep:
    """The run's step: replayed as a CUDA graph when `asked` (--cuda-graph) and the run allows it; otherwise the step
    itself, with a warning that says why when it was asked."""
    if not asked:
        return step
    why = not_replayable(step)
    if why is not None:
        warnings.warn(f"--cuda-graph: a training step cannot be replayed as a CUDA graph {why}; it runs as it is",
                      RuntimeWarning, stacklevel=2)
        return step
    return GraphedStep(step)


__all__ = ["GraphedStep", "CudaGraphs", "GraphBackend", "CaptureFailed", "graphed", "not_replayable", "WARM_STEPS"]
