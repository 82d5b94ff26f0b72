"""A CUDA graph's stand-in on the CPU, for graphed_step.GraphedStep: `ReplayRecorder` runs the captured work at the
capture and again at each replay, recording each time what it launched, and raises `NotReplayable` when a replay's
record differs from the capture's.

A CUDA graph replays its capture's kernels with the capture's arguments. So the record holds, in order, every torch
operator and every Warp launch, with its numbers as they are and each tensor or array argument as one of:

- "made": its memory was made inside the work (by an operator before it). A graph's own memory holds it, at the
  same place at every replay; the record keeps only its shape;
- "kept": memory made before the work (the parameters, Adam's state, the graph's fixed inputs). The record keeps
  its address: a graph would read the capture's.

A replay that differs shows what a real graph would get wrong: a number that changes from step to step (a learning
rate given as a number), or an input that is not copied into a fixed place (a view's own photo or camera, a rate
put in a new tensor). The pair rooms are told the work is being captured, as they are on a GPU, so that a room
follows the counts of replays only as the graphed step tells it to (PairRoom.replayed).
"""

from __future__ import annotations

from typing import Any, Callable

import torch
import warp as wp
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from mcsplat.compute.runtime import array_t
from mcsplat.render.bin import pair_room, warp_kernels


_NUMBERS_AND_NAMES = (bool, int, float, complex, str, torch.dtype, torch.device, torch.layout, torch.memory_format)


class NotReplayable(AssertionError):
    pass


class _Recording(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.made: list[tuple[int, int]] = []  # [start, end) of the memory made inside the work
        self.entries: list[tuple] = []

    def _is_made(self, address: int) -> bool:
        return any(start <= address < end for start, end in self.made)

    def place(self, address: int, shape: tuple, what: Any) -> tuple:
        if address == 0 or 0 in shape:  # no memory (a 0-d tensor has one number: it counts)
            return ("empty", shape, what)
        return ("made", shape, what) if self._is_made(address) else ("kept", address, shape, what)

    def describe(self, value: Any) -> Any:
        if isinstance(value, torch.Tensor):
            return self.place(value.data_ptr(), tuple(value.shape), (value.dtype, value.stride()))
        if isinstance(value, array_t):
            return self.place(value.data, tuple(value.shape)[:value.ndim], "warp")
        if isinstance(value, wp.array):
            return self.place(value.ptr, tuple(value.shape), "warp")
        if isinstance(value, (list, tuple)):
            return tuple(self.describe(item) for item in value)
        if isinstance(value, dict):
            return tuple((key, self.describe(item)) for key, item in sorted(value.items()))
        if isinstance(value, torch.Generator):
            return ("generator", value.device)  # (a new Python object for the same generator at each call)
        if isinstance(value, _NUMBERS_AND_NAMES) or value is None:
            return value
        return type(value).__name__  # the profiler's handles of Optimizer.step's record_function, ...

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.entries.append((str(func), self.describe(args), self.describe(kwargs)))
        out = func(*args, **kwargs)
        inputs = {t.untyped_storage().data_ptr() for t in tree_leaves((args, kwargs)) if isinstance(t, torch.Tensor)}
        for tensor in tree_leaves(out):
            if isinstance(tensor, torch.Tensor):
                storage = tensor.untyped_storage()
                if storage.data_ptr() and storage.data_ptr() not in inputs:
                    self.made.append((storage.data_ptr(), storage.data_ptr() + storage.nbytes()))
        return out

    def launched(self, kernel, dim, inputs) -> None:
        self.entries.append((getattr(kernel, "key", str(kernel)), dim, self.describe(list(inputs))))

    def sorted_pairs(self, keys, values, count, end_bit) -> None:
        self.entries.append(("radix_sort_pairs", self.describe((keys, values)), count, end_bit))


def record(work: Callable[[], Any]) -> list[tuple]:
    """What `work` launched: its operators, Warp launches and radix sorts, in order (run with set_cpu_threads(1), so
    that the launches of a thread pool come in one order). The pair rooms are told they are being captured, as on a
    GPU: what a capture runs once (the room's Python), a replay does not run."""
    recording = _Recording()
    launch, launch_tiled, sort = wp.launch, wp.launch_tiled, warp_kernels.radix_sort_pairs

    def recorded(real):
        def launch_recorded(kernel, dim=None, inputs=(), **options):
            recording.launched(kernel, dim, inputs)
            return real(kernel, dim=dim, inputs=inputs, **options)
        return launch_recorded

    def sort_recorded(keys, values, count, end_bit):
        recording.sorted_pairs(keys, values, count, end_bit)
        return sort(keys, values, count, end_bit)

    wp.launch, wp.launch_tiled, warp_kernels.radix_sort_pairs = recorded(launch), recorded(launch_tiled), sort_recorded
    capturing, pair_room.capturing = pair_room.capturing, lambda device: True
    try:
        with recording:
            work()
    finally:
        wp.launch, wp.launch_tiled, warp_kernels.radix_sort_pairs = launch, launch_tiled, sort
        pair_room.capturing = capturing
    return recording.entries


class ReplayRecorder:
    """graphed_step.GraphBackend on the CPU: captures by running and recording the work, replays by running it again
    and checking that it did the same."""

    def __init__(self) -> None:
        self.work: Callable[[], Any] | None = None
        self.recorded: list[tuple] = []
        self.captures = self.replays = 0

    def settle(self) -> None:
        pass

    def capture(self, work: Callable[[], Any]) -> None:
        self.work, self.recorded = work, record(work)
        self.captures += 1

    def replay(self) -> None:
        again = record(self.work)
        self.replays += 1
        if again != self.recorded:
            raise NotReplayable(_first_difference(self.recorded, again))


def _first_difference(captured: list[tuple], replayed: list[tuple]) -> str:
    for index, (then, now) in enumerate(zip(captured, replayed)):
        if then != now:
            return f"entry {index} of the capture's {len(captured)} differs at a replay:\n  {then}\n  {now}"
    return f"the capture did {len(captured)} things, the replay {len(replayed)}"
