"""The protocol the trainer drives; MCMC (the paper) and ADC (the 3DGS baseline) both implement it.

Per training step the trainer calls, in this order:

    loss = photometric_loss + strategy.regularization(model)
    loss.backward()
    strategy.step_post_backward(step, model, render_result, width, height)
    for each optimizer: optimizer.step(); optimizer.zero_grad(set_to_none=True)
    report = strategy.step_post_optimizer(step, model, optimizers, means_lr)

Steps are 0-based; the report says what the strategy did (RefineReport). When and up to how many Gaussians it
refines is its schedule (MCMCSchedule, ADCSchedule), which the run's plan gives it and hands it again through
`follow` whenever it plans again (--budget). A strategy's `collective` attribute (ALONE
by default) is how it agrees with the other processes when several train one model (mcsplat.distributed).
Strategies may replace the model's Parameters (through mcsplat.optim), so the trainer must read parameters through
the model after each step rather than keep references to them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, ClassVar, Hashable, Mapping, Protocol, runtime_checkable

import torch

from ..gaussians import GaussianModel
from ..render.project import deferred

__all__ = ["Strategy", "Collective", "ALONE", "RefineReport", "Schedule", "AT_STEP", "EVERY", "DECAY", "PLANNED",
           "asks_the_scene", "changed", "l1_regularizers"]

# What a field of a strategy's schedule is, as its metadata: how a run's plan fits it to the run's length (a run of N
# steps takes the paper's 30,000-step values times N / 30,000: planning/schedule.py) and plans it again (--budget).
AT_STEP = {"schedule": "at step"}  # a step of the run: scaled and rounded
EVERY = {"schedule": "every"}  # an interval: scaled, rounded, at least one step
DECAY = {"schedule": "decay"}  # a factor per step: raised to the inverse scale, the same decay over the run
PLANNED = {"schedule": "planned"}  # planned with the others (a growth rate), not scaled


class Schedule:
    """A strategy's schedule (a frozen dataclass whose fields say what they are in their metadata): it scales and
    lists itself, so that the plan (planning/) handles any strategy's the same way."""

    def scaled(self, numerator: int, denominator: int) -> Any:
        """Every scheduled field times numerator / denominator, as its kind says (the others as they are)."""
        def value(f: Any) -> Any:
            kind, current = f.metadata.get("schedule"), getattr(self, f.name)
            if kind == "at step":
                return round(current * numerator / denominator)
            if kind == "every":
                return max(1, round(current * numerator / denominator))
            if kind == "decay":
                return current ** (denominator / numerator)
            return current

        return type(self)(**{f.name: value(f) for f in fields(self)})

    def entries(self) -> dict[str, Any]:
        """The scheduled fields' values, by name (what --budget plans again)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if "schedule" in f.metadata}

    def with_entries(self, values: Mapping[str, Any]) -> Any:
        """The schedule with the scheduled fields of `values`."""
        return type(self)(**{f.name: values.get(f.name, getattr(self, f.name)) if "schedule" in f.metadata
                             else getattr(self, f.name) for f in fields(self)})


class Collective(Protocol):
    """What a strategy needs from the other training processes when several train one model (mcsplat.distributed):
    every process takes the same decisions, from the same parameters and the same generator."""

    def agree(self, indices: torch.Tensor) -> torch.Tensor:
        """Rank 0's `indices` on every process: a guard that sampled decisions (relocation, growth) are the same."""
        ...

    def sum_(self, tensor: torch.Tensor) -> None:
        """In place: the sum of the processes' tensors (statistics gathered from each process's own views)."""
        ...

    def max_(self, tensor: torch.Tensor) -> None:
        """In place: the element-wise maximum of the processes' tensors."""
        ...


class _Alone:
    """A single process: nothing to agree on."""

    def agree(self, indices: torch.Tensor) -> torch.Tensor:
        return indices

    def sum_(self, tensor: torch.Tensor) -> None:
        pass

    def max_(self, tensor: torch.Tensor) -> None:
        pass


ALONE: Collective = _Alone()


@dataclass(frozen=True)
class RefineReport:
    """What a strategy did after one optimizer step. Each strategy subclasses it with its own named counts (int
    fields); the fields named in LEVELS describe a state rather than count events."""

    num_gaussians: int  # after the step
    LEVELS: ClassVar[tuple[str, ...]] = ()

    def counts(self) -> dict[str, int]:
        """Gaussians changed this step, by what happened (a log record sums them over its steps)."""
        return {f.name: int(getattr(self, f.name)) for f in fields(self)
                if f.name != "num_gaussians" and f.name not in self.LEVELS}

    def levels(self) -> dict[str, float]:
        """The levels measured at this step (a log record keeps the last one)."""
        return {name: getattr(self, name) for name in self.LEVELS if getattr(self, name) is not None}


def changed(report: RefineReport) -> bool:
    """Whether the step did anything worth an event: a non-zero count or a level measured."""
    return any(report.counts().values()) or any(report.levels().values())


def asks_the_scene(strategy: Any) -> bool:
    """Whether `strategy` stops growing where the scene asks for no more (MCMC without a number for its cap, or
    with relocation "alive"); its `chosen_cap` is then where it stopped, and `ceiling` the most it allowed."""
    return bool(getattr(strategy, "asks_the_scene", False))


def graph_phase(strategy: Any, step: int) -> Hashable | None:
    """What the strategy's per-step work branches on at `step` (strategy.graph_phase), for a step replayed as a CUDA
    graph: a step whose phase matches its graph's capture is replayed. None for a step that must run as it is, and
    for a strategy that does not say."""
    said = getattr(strategy, "graph_phase", None)
    return said(step) if said is not None else None


@runtime_checkable
class Strategy(Protocol):
    def regularization(self, model: GaussianModel) -> torch.Tensor:
        """A scalar added to the loss (the MCMC regularizers; zero for ADC)."""
        ...

    def step_post_backward(self, step: int, model: GaussianModel, render_result: Any, width: int,
                           height: int) -> None:
        """After loss.backward(), before the Adam steps (ADC gathers its screen-space gradient statistics)."""
        ...

    def step_post_optimizer(self, step: int, model: GaussianModel, optimizers: Mapping[str, torch.optim.Optimizer],
                            means_lr: float | torch.Tensor) -> RefineReport:
        """After the Adam steps: densify / relocate / add noise as due; says what it did. `means_lr` is the rate the
        noise follows, a tensor of one on the device in a step replayed as a CUDA graph."""
        ...

    def follow(self, schedule: Any) -> None:
        """Refine on `schedule` (the strategy's own schedule type, from the run's plan) from the next step on."""
        ...

    def state_dict(self) -> dict:
        ...

    def load_state_dict(self, state: dict) -> None:
        ...


def l1_regularizers(model: GaussianModel, opacity_reg: float, scale_reg: float) -> torch.Tensor:
    """The MCMC paper's Eq. 10 as its code has it: opacity_reg mean(sigmoid(o)) + scale_reg mean(exp(s)), means of
    the activated values (the paper writes sums). Zero for an empty model or zero weights."""
    if model.num_gaussians == 0 or (opacity_reg == 0 and scale_reg == 0):
        return model.means.new_zeros(())
    left = deferred.regularizers_left_to_update(model.params["log_scales"], model.params["opacity_logits"],
                                                opacity_reg, scale_reg)  # the CPU's fused update adds the gradient
    if left is not None:
        return left
    return opacity_reg * model.opacities.mean() + scale_reg * model.scales.mean()
