"""Room for the Warp binning's (tile, Gaussian) pairs, sized ahead, so that a training step's render never reads its
pair count.

The pair lists' length is known only once the Gaussians have been projected and counted on the device. Reading it
back makes the host wait for every kernel queued before, at every render, and a step whose sizes depend on a value
read in it cannot be captured as a CUDA graph. So inside `sized_ahead()` (the training step's render) the lists get
a room of a fixed size, per image size:

- the first render at a size reads its count (once);
- every render queues a copy of its count to the host (pinned memory on CUDA, with an event), and a later render at
  that size reads the copy only when the event says it has arrived, so it never waits;
- the room holds a quarter more (HEADROOM) than the most pairs per Gaussian among the last 64 counts that arrived,
  times the Gaussians of the render at hand: it grows with the model before a render needs it, and shrinks only when
  none of those counts needed a third of it (the radix sort walks the whole room);
- a render whose pairs do not fit writes the front ones: slots are given front to back, so what is dropped are the
  farthest Gaussians' pairs, from the renders before the count arrives (the room counts them in `overflows`, and the
  first one warns).

Every other render (evaluation, the viewer, exports) reads its count and lists every pair, as before.

A step captured as a CUDA graph (graphed_step.py) runs the render's Python once, at the capture: the graph's copy of
the count is queued at every replay, but the event that says it arrived cannot be recorded inside a capture. So a
capture leaves the room `captured`, and the step calls its `replayed()` after each replay (the event), and sizes it
(`room_at(...).size`) before it (a room that has to change size needs a new capture).

The CPU's own binning (cpu_loops.py) reads the count as it goes, which costs nothing there; this room serves the Warp
kernels, which CUDA runs (and the CPU with set_cpu_kernels("scalar")).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import warnings
from collections import deque
from dataclasses import dataclass, field
from typing import Iterator

import torch

HEADROOM = 1.25  # room for a quarter more pairs than the most a Gaussian has brought lately, times the Gaussians
WINDOW = 64  # the counts the room follows: the most pairs per Gaussian among the last this many that arrived
SHRINK_BELOW = 1 / 3  # the room shrinks when what it follows needs less than this share of it
MIN_ROOM = 4096  # pairs: a room is never smaller (an empty first render does not leave one of size 0)
ROOMS_KEPT = 8  # image sizes whose rooms are kept (coarse to fine moves through many sizes; the newest are kept)


@dataclass
class PairRoom:
    """The room of one image size on one device: `capacity` pairs, sized from the pairs per Gaussian of its last
    WINDOW counts (so that it follows the model's growth before a render needs it), and the copy of the last count
    on its way to the host."""

    capacity: int
    device: torch.device
    overflows: int = 0  # renders whose pairs did not all fit (seen one render late or more)
    _ratios: deque = field(default_factory=lambda: deque(maxlen=WINDOW), repr=False)  # pairs per Gaussian
    _copy: torch.Tensor = field(init=False, repr=False)  # int64 [1] on the host: the last render's count
    _on_its_way: tuple[int, int] | None = field(default=None, init=False, repr=False)  # its Gaussians and room
    _arrived: torch.cuda.Event | None = field(default=None, init=False, repr=False)
    _captured: tuple[int, int] | None = field(default=None, init=False, repr=False)  # a graph's Gaussians and room

    def __post_init__(self) -> None:
        self._copy = torch.zeros(1, dtype=torch.int64, pin_memory=self.device.type == "cuda")

    def size(self, gaussians: int) -> int:
        """The room for a render of `gaussians`: the last count, once it has arrived, joins those it follows."""
        if self._on_its_way is not None and (self._arrived is None or self._arrived.query()):
            (then, room), self._on_its_way = self._on_its_way, None
            self.follow(self._copy.item(), then, room)
        if self._ratios:
            needed = _room_for(max(self._ratios) * gaussians)
            if needed > self.capacity or needed < SHRINK_BELOW * self.capacity:
                self.capacity = needed
        return self.capacity

    def counted(self, total: torch.Tensor, gaussians: int) -> None:
        """Queue the copy of this render's count (int64 [1] or [] on the device) to the host."""
        self._copy.copy_(total.reshape(1), non_blocking=self.device.type == "cuda")
        if capturing(self.device):
            self._captured = (gaussians, self.capacity)  # each replay queues the copy; replayed() says so
            return
        self._note_on_its_way(gaussians, self.capacity)

    def replayed(self) -> None:
        """A graph holding this room's render was replayed: the copy of its count is on its way (a graph is replayed
        only with the Gaussians and the room of its capture, graphed_step.py)."""
        if self._captured is not None:
            self._note_on_its_way(*self._captured)

    def _note_on_its_way(self, gaussians: int, room: int) -> None:
        if self.device.type == "cuda":
            self._arrived = torch.cuda.Event()
            self._arrived.record(torch.cuda.current_stream(self.device))
        self._on_its_way = (gaussians, room)

    def follow(self, count: int, gaussians: int, room: int) -> None:
        """A render of `gaussians` in a room of `room` counted `count` pairs."""
        self._ratios.append(count / max(gaussians, 1))
        if count > room:
            self.overflows += 1
            if self.overflows == 1:
                warnings.warn(f"a training step's render had {count:,} tile pairs, more than the {room:,} its room "
                              f"held: its farthest pairs were left out of that step; the room has grown",
                              RuntimeWarning, stacklevel=2)

    def host_copy(self) -> torch.Tensor:
        """The host tensor the counts are copied into (what `size` reads; no device is read there)."""
        return self._copy


def capturing(device: torch.device) -> bool:
    """Whether the render is being captured as a CUDA graph (tests/support/graph_check.py says so on the CPU)."""
    return device.type == "cuda" and torch.cuda.is_current_stream_capturing()


def _room_for(pairs: float) -> int:
    return max(MIN_ROOM, math.ceil(HEADROOM * pairs))


_rooms: dict[tuple[torch.device, int, int], PairRoom] = {}
_sized_ahead: contextvars.ContextVar[bool] = contextvars.ContextVar("pairs_sized_ahead", default=False)


@contextlib.contextmanager
def sized_ahead() -> Iterator[None]:
    """Renders in here put their pairs in the rooms (no count read back); the training step renders in here."""
    token = _sized_ahead.set(True)
    try:
        yield
    finally:
        _sized_ahead.reset(token)


def is_sized_ahead() -> bool:
    return _sized_ahead.get()


def room(device: torch.device, tiles_x: int, tiles_y: int, total: torch.Tensor, gaussians: int) -> PairRoom:
    """The room of this image size (in tiles) on `device`, made on its first render from the count `total` of its
    `gaussians`, which is read then (the only read of a count a size's renders make)."""
    key = (device, tiles_x, tiles_y)
    found = _rooms.pop(key, None)
    if found is None:
        count = int(total)
        found = PairRoom(_room_for(count), device)
        found.follow(count, gaussians, found.capacity)
        if len(_rooms) >= ROOMS_KEPT:
            _rooms.pop(next(iter(_rooms)))
    _rooms[key] = found  # the newest last
    return found


def room_at(device: torch.device, tiles_x: int, tiles_y: int) -> PairRoom | None:
    """The room of this image size (in tiles), None before the size's first training render (a step captured as a
    graph asks for it before each replay: another room, or another size of it, needs a new capture)."""
    return _rooms.get((device, tiles_x, tiles_y))


def forget_rooms() -> None:
    """Drop every room: a training run starts from none (another run's model, or --budget's probes, need others)."""
    _rooms.clear()
