"""The SGLD noise of the MCMC method (the paper's Eqs. 7-8) and the variants its rebuttal and Table 3 ablate.

The method: every step, means += lambda_noise x lr(t) x gate(o) x Sigma eta, eta ~ N(0, I3), with lr(t) the position
learning rate (exponential decay), gate(o) = sigmoid(-100 (o - 0.005)) and Sigma the full covariance. The ablations
(docs/paper.md measures them), each an MCMCConfig option:

- noise_covariance=False: the Sigma factor dropped, means += lambda_noise lr(t) gate(o) eta (the paper's "without the
  covariance"; the noise no longer follows each Gaussian's shape and size);
- noise_gated=False: every Gaussian moves, not only the nearly transparent ones (the paper could train it only with
  lambda_noise = 0.05);
- noise_all_params=True: Table 3's "noise on all parameters": also N(0, 1) on the log-scales and the rotation
  quaternions and N(0, 0.1^2) on the opacity logits, each decayed x0.9995 per step of a 30,000-step run
  (param_noise_decay, fitted to the run's length with the other schedules). The paper does not say whether the
  opacity gate applies to them; here it does, as it does to the positions (ungated unit noise on every log-scale
  would undo any training, far worse than the small loss the paper reports: docs/paper.md, "4. The noise");
- noise_schedule: "lr" (the paper: the position learning rate's exponential decay), "linear" (the same start and end
  values joined by a straight line) or "neelakantan" (Neelakantan et al. 2015, a variance decaying as
  (1 + t)^-0.55, t counted in steps of a 30,000-step run).
"""

from __future__ import annotations

import math
from typing import Literal, get_args

import torch

from ..gaussians import GaussianModel
from ..optim import OptimConfig, means_lr_at
from . import position_noise_simd

__all__ = ["NOISE_SCHEDULES", "NoiseSchedule", "noise_gate", "inject_position_noise", "inject_parameter_noise",
           "noise_lr_at", "NOISE_GATE_K", "NOISE_GATE_CENTER"]

# The noise gate sigmoid(-k (o - t)), k = 100, t = 0.005: the official code's, not the paper's printed t = 0.995.
NOISE_GATE_K = 100.0
NOISE_GATE_CENTER = 0.005
NoiseSchedule = Literal["lr", "linear", "neelakantan"]
NOISE_SCHEDULES: tuple[str, ...] = get_args(NoiseSchedule)
NEELAKANTAN_GAMMA = 0.55      # the variance decays as (1 + t)^-gamma, so the standard deviation as its square root
PAPER_STEPS = 30_000
OPACITY_NOISE_STD = 0.1       # Table 3's all-parameters variant: "N(0, 0.1)" on the opacity, taken as the std
SHAPE_NOISE_STD = 1.0         # ... and N(0, 1) on the scale and the rotation


def noise_gate(opacities: torch.Tensor) -> torch.Tensor:
    """sigmoid(-100 (o - 0.005)): about 0.5 at o = 0.005, 0.011 at 0.05, ~3e-22 at 0.5."""
    return torch.sigmoid(-NOISE_GATE_K * (opacities - NOISE_GATE_CENTER))


def _gate(model: GaussianModel, gated: bool) -> torch.Tensor:
    return noise_gate(model.opacities) if gated else model.opacities.new_ones(model.num_gaussians)


def _normal(shape: tuple[int, ...], generator: torch.Generator, like: torch.Tensor) -> torch.Tensor:
    drawn = torch.randn(shape, generator=generator, device=generator.device, dtype=like.dtype)
    return drawn if drawn.device == like.device else drawn.to(like.device)


@torch.no_grad()
def inject_position_noise(model: GaussianModel, factor: float | torch.Tensor, generator: torch.Generator, *,
                          covariance: bool = True, gated: bool = True) -> None:
    """means += factor x gate(o) x Sigma eta (Sigma dropped without `covariance`, the gate without `gated`).

    `factor` is lambda_noise x the noise schedule's learning rate: a number, or a tensor of one on the device (a step
    replayed as a CUDA graph changes it there). Sigma is the full covariance (not its square
    root). Only the positions change, in place, bypassing the optimizer: its state is untouched. eta is torch's
    draw from `generator`, or on the CPU's float32 runs the kernel's own from a key drawn from it
    (position_noise_simd.py).
    """
    n = model.num_gaussians
    if n == 0 or (not isinstance(factor, torch.Tensor) and factor == 0):
        return
    means = model.params["means"]
    if position_noise_simd.takes(model.params, factor):  # the CPU's float32 runs: one kernel draws and adds
        key = position_noise_simd.draw_key(generator)
        position_noise_simd.add_position_noise(model.params, key, factor, covariance=covariance, gated=gated,
                                               gate_k=NOISE_GATE_K, gate_center=NOISE_GATE_CENTER)
        return
    eta = _normal((n, 3), generator, means)
    shaped = model.covariance_times(eta) if covariance else eta
    means.add_(shaped * (factor * _gate(model, gated))[:, None])


@torch.no_grad()
def inject_parameter_noise(model: GaussianModel, strength: float, generator: torch.Generator, *,
                           gated: bool = True) -> None:
    """Table 3's noise on the other parameters: log-scales and quaternions += strength x gate(o) x N(0, 1), opacity
    logits += strength x gate(o) x N(0, 0.1^2). The gate is that of the opacities before any of it is added."""
    n = model.num_gaussians
    if n == 0 or strength == 0:
        return
    gate = strength * _gate(model, gated)
    stds = {"log_scales": SHAPE_NOISE_STD, "quats": SHAPE_NOISE_STD, "opacity_logits": OPACITY_NOISE_STD}
    for key, std in stds.items():
        param = model.params[key]
        noise = _normal(tuple(param.shape), generator, param) * std
        param.add_(noise * gate.view(-1, *([1] * (param.dim() - 1))))


def noise_lr_at(schedule: str, step: int, steps: int, optim: OptimConfig, scene_radius: float) -> float:
    """The learning rate the position noise follows at `step` of a `steps`-step run (times lambda_noise it is the
    noise factor). "lr" is the position learning rate itself, the paper's; the others start where it starts."""
    if schedule == "lr":
        return means_lr_at(step, steps, optim, scene_radius)
    start, end = means_lr_at(0, steps, optim, scene_radius), means_lr_at(steps, steps, optim, scene_radius)
    t = min(max(step / steps, 0.0), 1.0)
    if schedule == "linear":
        return start + (end - start) * t
    if schedule == "neelakantan":
        return start * math.pow(1.0 + t * PAPER_STEPS, -NEELAKANTAN_GAMMA / 2.0)
    raise ValueError(f"unknown noise schedule {schedule!r}: choose one of {', '.join(NOISE_SCHEDULES)}")
