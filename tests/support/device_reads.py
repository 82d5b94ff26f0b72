"""A device that refuses reads, on the CPU: under `RefuseReads()`, reading a tensor's values on the host raises
`DeviceRead`. On a GPU each such read makes the host wait for every kernel queued before it, and a CUDA graph cannot
hold it; a CPU test catches them here before a GPU does.

What counts as a read: item, tolist, numpy, bool / int / float / index of a tensor, nonzero, and the ops whose
output size depends on values (indexing with a boolean mask, masked_select, bincount, unique, repeat_interleave
without its output size). Tensors the code keeps on the host on purpose (a copy queued a step before, which on a GPU
lives in pinned memory) are named in `host`, and reading them is allowed and counted.

Copies the other way wait too: a copy from pageable host memory to a GPU waits for the queue. So Python numbers made
into a tensor on a device (torch.tensor / as_tensor of them with a device) are refused as well. A `.to(device)` of a
host tensor waits the same way, but on the CPU it cannot be told from one of a tensor already on the device (a no-op
there); the tests check the step's own uploads (its camera, its image) where they are made.
"""

from __future__ import annotations

import traceback
from typing import Iterable

import torch
from torch.overrides import TorchFunctionMode


class DeviceRead(AssertionError):
    pass


_READS = {torch.Tensor.item, torch.Tensor.tolist, torch.Tensor.numpy, torch.Tensor.__bool__, torch.Tensor.__int__,
          torch.Tensor.__float__, torch.Tensor.__index__, torch.Tensor.nonzero, torch.nonzero, torch.argwhere,
          torch.Tensor.masked_select, torch.masked_select, torch.bincount, torch.Tensor.bincount, torch.unique,
          torch.Tensor.unique, torch.unique_consecutive, torch.Tensor.unique_consecutive}
_SIZED_BY_VALUES = {torch.repeat_interleave, torch.Tensor.repeat_interleave}  # unless output_size is given
_INDEXING = {torch.Tensor.__getitem__, torch.Tensor.__setitem__}
_FROM_PYTHON = {torch.tensor, torch.as_tensor}


def _waits_to_upload(func, args, kwargs) -> bool:
    return func in _FROM_PYTHON and "device" in kwargs and not isinstance(args[0], torch.Tensor)


def _boolean_index(index) -> bool:
    parts = index if isinstance(index, tuple) else (index,)
    return any(isinstance(part, torch.Tensor) and part.dtype == torch.bool for part in parts)


class RefuseReads(TorchFunctionMode):
    def __init__(self, host: Iterable[torch.Tensor] = ()):
        super().__init__()
        self._host = {id(tensor) for tensor in host}
        self.host_reads = 0  # reads of the tensors named in `host`

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        reads = (func in _READS or (func in _SIZED_BY_VALUES and "output_size" not in kwargs)
                 or (func in _INDEXING and len(args) > 1 and _boolean_index(args[1])))
        if _waits_to_upload(func, args, kwargs):
            where = "".join(traceback.format_stack(limit=6)[:-1])
            raise DeviceRead(f"{getattr(func, '__name__', func)} copies to a device and waits:\n{where}")
        if reads:
            if args and isinstance(args[0], torch.Tensor) and id(args[0]) in self._host:
                self.host_reads += 1
            else:
                where = "".join(traceback.format_stack(limit=6)[:-1])
                raise DeviceRead(f"{getattr(func, '__name__', func)} reads a tensor on the host:\n{where}")
        return func(*args, **kwargs)
