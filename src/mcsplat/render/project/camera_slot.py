"""A fixed place on the device for a camera's packed numbers (cpu_simd.CAMERA_LAYOUT), for a training step replayed
as a CUDA graph (graphed_step.py).

A graph replays its kernels with the arguments of its capture, so the projection kernels must read every view's
camera from the same array. While a slot is `serving()`, packed_camera (warp_kernel.py) asks it first:
- an empty slot notes the render's settings (image size, near and far planes, low-pass filter) and lets the camera's
  own array serve (the steps before a capture);
- once filled (warp_kernel.fill_slot, a copy on the device, before the capture and before each replay) it hands out
  its own array.
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

import torch

from .cpu_simd import CAMERA_LAYOUT

_serving: contextvars.ContextVar["CameraSlot | None"] = contextvars.ContextVar("camera_slot", default=None)


class CameraSlot:
    def __init__(self, dtype: torch.dtype, device: torch.device):
        self.buffer = torch.zeros(len(CAMERA_LAYOUT), dtype=dtype, device=device)
        # (width, height, tiles_x, tiles_y, near, far, eps2d) of the renders it served: the same for each
        self.settings: tuple | None = None
        self.filled = False  # whether it holds a camera (warp_kernel.fill_slot)

    @contextlib.contextmanager
    def serving(self) -> Iterator[CameraSlot]:
        """Renders in here read their camera from this slot."""
        token = _serving.set(self)
        try:
            yield self
        finally:
            _serving.reset(token)

    def serve(self, camera_args: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor | None:
        """The slot's array for a render of `camera_args` (warp_kernel._camera_arguments), whose settings it keeps;
        None while it is empty."""
        if dtype != self.buffer.dtype or torch.device(device) != self.buffer.device:
            raise ValueError(f"a camera slot of {self.buffer.dtype} on {self.buffer.device} cannot serve a render in "
                             f"{dtype} on {device}")
        settings = tuple(camera_args[7:])
        if self.settings is None:
            self.settings = settings
        elif settings != self.settings:
            raise ValueError(f"a camera slot serves renders of one size and one setting, {self.settings}; this one "
                             f"has {settings}")
        return self.buffer if self.filled else None


def serving() -> CameraSlot | None:
    """The slot the renders read their camera from now, if any."""
    return _serving.get()
