"""The projection's parameter gradients left to the optimizer step, for an update that finishes them and applies
Adam in the same pass over the Gaussians (optim/fused_projection.py).

Within `deferring(deferral)`, a render whose projection reads `deferral`'s parameters (the
model's positions, rotations, DC and rest SH bands as stored, and its scales as exp of its log-scales) keeps what
its backward receives (the gradients of the 2D means, conics, depths, colours and compensations) in
`deferral.pending` and hands autograd no gradient for those parameters: their `.grad` holds only what the other
terms (regularizers, --surface) gave them. The update then owes them the projection's share. One projection a
deferral: a second render in the same step backs up as usual. A camera being refined (--pose-opt) needs the
backward's view gradient within autograd's pass, so its projection is never deferred.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Iterator

import torch


@dataclass
class DeferredBackward:
    """The projection backward's inputs, kept for the update: the SIMD kernel's on the CPU (`simd`), else the Warp
    kernel's (CUDA; the CPU's scalar kernels)."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor  # exp(log_scales), as the projection read them
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor
    camera_args: tuple  # warp_kernel._camera_arguments
    camera: torch.Tensor  # packed as cpu_simd.CAMERA_LAYOUT, on the device (warp_kernel.packed_camera)
    sh_degree: int
    antialiased: bool
    colors: torch.Tensor | None  # the forward's (the SIMD backward reads them for the clamp)
    upstream: list[torch.Tensor]  # gradients of means2d, conics, depths, colours, compensations
    simd: bool

    @property
    def width(self) -> int:
        return self.camera_args[7]

    @property
    def height(self) -> int:
        return self.camera_args[8]


class Deferral:
    """One step's deferred projection backward: the parameters it stands for, and what the backward left."""

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, sh0: torch.Tensor,
                 sh_rest: torch.Tensor):
        self.means, self.quats, self.log_scales, self.sh0, self.sh_rest = means, quats, log_scales, sh0, sh_rest
        self.taken = False  # a projection has deferred to it
        self.pending: DeferredBackward | None = None

    def accepts(self, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, sh_dc: torch.Tensor,
                sh_rest: torch.Tensor | None) -> bool:
        """Whether a projection of these inputs can defer: the first of the step, of this deferral's own parameters
        (the tensors themselves, contiguous; the scales one exp of the log-scales)."""
        if self.taken or sh_rest is None:
            return False
        same = all(a is b and a.is_contiguous() for a, b in (
            (means, self.means), (quats, self.quats), (sh_dc, self.sh0), (sh_rest, self.sh_rest)))
        return same and scales.is_contiguous() and _exp_of(scales, self.log_scales)


def _exp_of(tensor: torch.Tensor, leaf: torch.Tensor) -> bool:
    """Whether autograd made `tensor` as exp(leaf) directly (so that its gradient reaches leaf times `tensor`)."""
    node = tensor.grad_fn
    if node is None or type(node).__name__ != "ExpBackward0" or len(node.next_functions) != 1:
        return False
    source = node.next_functions[0][0]
    return source is not None and getattr(source, "variable", None) is leaf


_current: ContextVar[Deferral | None] = ContextVar("mcsplat_deferred_projection", default=None)


def current() -> Deferral | None:
    """The deferral that renders of this context may defer to (None outside `deferring`)."""
    return _current.get()


@contextmanager
def deferring(deferral: Deferral) -> Iterator[Deferral]:
    token = _current.set(deferral)
    try:
        yield deferral
    finally:
        _current.reset(token)
