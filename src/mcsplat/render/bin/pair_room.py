"""Room for the Warp binning's (tile, Gaussian) pairs, sized ahead, so that a training step's render never reads its
pair count.

The pair lists' length is known only once the Gaussians have been projected and counted on the device. Reading it
back makes the host wait for every kernel queued before, at every render, and a step whose sizes depend on a value
read in it cannot be captured as a CUDA graph. So inside `sized_ahead()` (the training step's render) the lists get
a room of a fixed size, per image size:

- the first render at a size reads its count (once) and takes a quarter more room than that (HEADROOM);
- every render queues a copy of its count to the host (pinned memory on CUDA, with an event), and the next render at
  that size reads the copy only when the event says it has arrived, so it never waits;
- when a count came near the room (GROW_AT) or past it, the room grows to the headroom over that count, and when it
  fell under a third of the room, the room shrinks to it (the radix sort walks the whole room);
- a render whose pairs do not fit writes the front ones: slots are given front to back, so what is dropped are the
  farthest Gaussians' pairs, from that step's render only (the room counts such renders in `overflows`).

Every other render (evaluation, the viewer, exports) reads its count and lists every pair, as before.

The CPU's own binning (cpu_loops.py) reads the count as it goes, which costs nothing there; this room serves the Warp
kernels, which CUDA runs (and the CPU with set_cpu_kernels("scalar")).
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from dataclasses import dataclass, field
from typing import Iterator

import torch

HEADROOM = 1.25  # room for a quarter more pairs than the count it was sized from
GROW_AT = 0.9  # a count above this share of the room grows it before one overflows
SHRINK_BELOW = 1 / 3  # a count below this share of the room shrinks it
ROOMS_KEPT = 8  # image sizes whose rooms are kept (coarse to fine moves through many sizes; the newest are kept)


@dataclass
class PairRoom:
    """The room of one image size on one device: `capacity` pairs, and the copy of the last count on its way."""

    capacity: int
    device: torch.device
    overflows: int = 0  # renders whose pairs did not all fit (seen one render late)
    _copy: torch.Tensor = field(init=False, repr=False)  # int64 [1] on the host: the last render's count
    _arrived: torch.cuda.Event | None = field(default=None, init=False, repr=False)
    _pending: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        self._copy = torch.zeros(1, dtype=torch.int64, pin_memory=self.device.type == "cuda")

    def size(self) -> int:
        """The room for this render: the last count that has arrived moves it first, when it should."""
        if self._pending and (self._arrived is None or self._arrived.query()):
            self._pending = False
            self._follow(self._copy.item())
        return self.capacity

    def counted(self, total: torch.Tensor) -> None:
        """Queue the copy of this render's count (int64 [1] or [] on the device) to the host."""
        self._copy.copy_(total.reshape(1), non_blocking=self.device.type == "cuda")
        if self.device.type == "cuda":
            self._arrived = torch.cuda.Event()
            self._arrived.record()
        self._pending = True

    def host_copy(self) -> torch.Tensor:
        """The host tensor the counts are copied into (what `size` reads; no device is read there)."""
        return self._copy

    def _follow(self, count: int) -> None:
        if count > self.capacity:
            self.overflows += 1
        if count > GROW_AT * self.capacity or count < SHRINK_BELOW * self.capacity:
            self.capacity = room_for(count)


def room_for(count: int) -> int:
    return max(1, math.ceil(HEADROOM * count))


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


def room(device: torch.device, tiles_x: int, tiles_y: int, total: torch.Tensor) -> PairRoom:
    """The room of this image size (in tiles) on `device`, made on its first render from the count `total`, which
    is read then (the only read of a count a size's renders make)."""
    key = (device, tiles_x, tiles_y)
    found = _rooms.pop(key, None)
    if found is None:
        found = PairRoom(room_for(int(total)), device)
        if len(_rooms) >= ROOMS_KEPT:
            _rooms.pop(next(iter(_rooms)))
    _rooms[key] = found  # the newest last
    return found


def forget_rooms() -> None:
    """Drop every room (tests start from none)."""
    _rooms.clear()
