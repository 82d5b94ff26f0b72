"""How a training step updates the Gaussians: a `ParameterUpdate` wraps the step's render and loss (`rendering`) and
takes the optimizers' step after the backward (`step`). The plain update lets autograd finish every gradient and steps
the optimizers (stepping.step_optimizers); on the CPU one process fuses the projection's backward with Adam
(fused_projection.py), the same result to the bit in one pass over the Gaussians."""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext
from typing import Mapping, Protocol

import torch

from .. import adam_cpu
from ..gaussians import GaussianModel
from . import fused_projection
from .fused_projection import FusedProjectionAdam
from .stepping import step_optimizers


class ParameterUpdate(Protocol):
    def rendering(self, model: GaussianModel) -> AbstractContextManager:
        """Around the step's render of `model` and its loss terms."""
        ...

    def step(self, optimizers: Mapping[str, torch.optim.Optimizer]) -> None:
        """After the backward: every optimizer's step, their gradients dropped."""
        ...


class PlainUpdate:
    def rendering(self, model: GaussianModel) -> AbstractContextManager:
        return nullcontext()

    def step(self, optimizers: Mapping[str, torch.optim.Optimizer]) -> None:
        step_optimizers(optimizers)


def update_for(device: torch.device, processes: int = 1) -> ParameterUpdate:
    """The fused update on the CPU, where adam_cpu's arithmetic is torch's, for one process (several average their
    gradients between the backward and the step, so each needs them whole); the plain one elsewhere."""
    if device.type == "cpu" and processes == 1 and adam_cpu.matches_torch():
        return FusedProjectionAdam()
    return PlainUpdate()


def training_kernels(device: torch.device) -> list:
    """The Warp kernels a step's update may launch on `device` (compute.compile loads them ahead)."""
    if device.type == "cpu" and adam_cpu.matches_torch():
        return list(adam_cpu.KERNELS) + list(fused_projection.KERNELS)
    return []
