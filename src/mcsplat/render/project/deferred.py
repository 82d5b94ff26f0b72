"""The projection's parameter gradients left to the optimizer step, for an update that finishes them and applies
Adam in the same pass over the Gaussians (optim/fused_projection.py).

Within `deferring(deferral)`, a render whose projection reads `deferral`'s parameters (the
model's positions, rotations, DC and rest SH bands as stored, and its scales as exp of its log-scales) keeps what
its backward receives (the gradients of the 2D means, conics, depths, colours and compensations) in
`deferral.pending` and hands autograd no gradient for those parameters: their `.grad` holds only what the other
terms (regularizers, --surface) gave them. The update then owes them the projection's share. One projection a
deferral: a second render in the same step backs up as usual. A camera being refined (--pose-opt) needs the
backward's view gradient within autograd's pass, so its projection is never deferred.

The L1 regularizers of the MCMC method may be left to the update too (`regularizers_left_to_update`): where the
SIMD projection deferred, it notes the scales and opacities it read, and the regularizers' value is taken from them
without autograd while the update adds their gradients (weight / count x exp(s) to the log-scales, weight / count x
sigmoid'(o) to the opacity logits) in its pass: one exp, one sigmoid and their backwards fewer a step.
"""

from __future__ import annotations

import functools
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
    opacities: torch.Tensor | None = None  # sigmoid(opacity logits) as the projection read them, with ...
    regularizers: tuple[float, float] | None = None  # ... the regularizers' gradient factors (opacity, scale)

    @property
    def width(self) -> int:
        return self.camera_args[7]

    @property
    def height(self) -> int:
        return self.camera_args[8]


class Deferral:
    """One step's deferred projection backward: the parameters it stands for, and what the backward left."""

    def __init__(self, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, sh0: torch.Tensor,
                 sh_rest: torch.Tensor, opacity_logits: torch.Tensor):
        self.means, self.quats, self.log_scales, self.sh0, self.sh_rest = means, quats, log_scales, sh0, sh_rest
        self.opacity_logits = opacity_logits
        self.taken = False  # a projection has deferred to it
        self.pending: DeferredBackward | None = None
        # (scales, opacities) the SIMD projection read, where they are exp and sigmoid of this deferral's parameters
        self.activations: tuple[torch.Tensor, torch.Tensor] | None = None
        self.regularizers: tuple[float, float] | None = None  # left to the update: (opacity, scale) factors

    def note_activations(self, scales: torch.Tensor, opacities: torch.Tensor) -> None:
        """The deferred SIMD projection's scales and opacities, kept for the regularizers where the opacities are
        one sigmoid of the opacity logits."""
        if opacities.is_contiguous() and _made_from(opacities, "SigmoidBackward0", self.opacity_logits):
            self.activations = (scales, opacities)

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
    return _made_from(tensor, "ExpBackward0", leaf)


def _made_from(tensor: torch.Tensor, node_name: str, leaf: torch.Tensor) -> bool:
    """Whether autograd made `tensor` by one operation (its backward node `node_name`) of `leaf` alone."""
    node = tensor.grad_fn
    if node is None or type(node).__name__ != node_name or len(node.next_functions) != 1:
        return False
    source = node.next_functions[0][0]
    return source is not None and getattr(source, "variable", None) is leaf


def regularizers_left_to_update(log_scales: torch.Tensor, opacity_logits: torch.Tensor, opacity_weight: float,
                                scale_weight: float) -> torch.Tensor | None:
    """opacity_weight mean(sigmoid(o)) + scale_weight mean(exp(s)) without autograd, its gradient left to the
    update, where this step's SIMD projection deferred with the activations of these parameters; else None (the
    caller differentiates it as usual). The gradient factors are the mean's backward as torch computes it: the
    weight in float32 divided by the count."""
    deferral = current()
    if (deferral is None or deferral.activations is None or deferral.regularizers is not None
            or deferral.log_scales is not log_scales or deferral.opacity_logits is not opacity_logits):
        return None
    scales, opacities = deferral.activations
    with torch.no_grad():
        value = opacity_weight * opacities.mean() + scale_weight * scales.mean()
    deferral.regularizers = (_mean_gradient(opacity_weight, opacities.numel()),
                             _mean_gradient(scale_weight, scales.numel()))
    return value


@functools.lru_cache(maxsize=16)
def _mean_gradient(weight: float, count: int) -> float:
    """d (weight mean(x)) / d x_i as autograd computes it in float32 (exact as a Python float; worked out once for a
    count of Gaussians)."""
    return float((torch.tensor([weight], dtype=torch.float32) / count)[0])


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
