"""One training step: `Step`, built once for a run with what every step shares, then called with what changes from
step to step, `step(index, view, plan)`.

One step (docs/method.md, "One training step"; in gsplat's order, see strategy/mcmc.py for how the official code
differs):
    render a training view (camera and render through the per-image modules, per_image.py: --pose-opt, --appearance)
    -> loss = the sum of the loss terms (loss_terms.py: 0.8 L1 + 0.2 D-SSIM over the pixels a mask keeps, strategy
    and module regularizers, the features' terms) -> backward -> strategy.step_post_backward (ADC gradient
    statistics) -> Adam steps -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD
    noise; ADC: densify / prune)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import torch

from . import losses, optim, render
from .appearance import training_kernels as appearance_kernels
from .camera import Camera
from .config import TrainConfig
from .data import View
from .errors import MCSplatError
from .gaussians import GaussianModel
from .loss_terms import LossTerm, StepContext, render_outputs, standard_terms, total_loss
from .metrics import StepValues, WithStepValues, psnr_on_device
from .optim import ParameterUpdate, PlainUpdate, means_lr_at, set_means_lr
from .per_image import PerImageModule
from .planning import Plan
from .render import RenderResult
from .strategy import Strategy, training_kernels as strategy_kernels
from .strategy.base import RefineReport
from .strategy.noise import noise_lr_at


@dataclass(frozen=True)
class StepInputs:
    """What a step reads of its view, on the device."""

    camera: Camera  # at the step's resolution, moved by the per-image modules
    target: torch.Tensor  # [H, W, 3] the photo at the camera's size
    keep: torch.Tensor | None  # [H, W, 1] the mask's weights; None when the scene has no masks


@dataclass
class StepResult(WithStepValues):
    values: StepValues  # the loss and train PSNR, read when asked
    refine: RefineReport  # what the strategy did after the optimizer step


Reduce = Callable[[GaussianModel, torch.Tensor], torch.Tensor]


def alone(model: GaussianModel, values: torch.Tensor) -> torch.Tensor:
    """The reduce of a process training alone: nothing to do."""
    return values


class FiniteLoss:
    """The losses of the steps since the last check, a row each in a buffer on the step's device, so that no step
    waits to read its loss; `check()` reads them (the trainer does every few steps and before a checkpoint; a step
    checks by itself when the buffer is full)."""

    ROWS = 64

    def __init__(self) -> None:
        self._rows: torch.Tensor | None = None  # [ROWS, k]: each step's reduced values, the loss first
        self._steps: list[int] = []  # the step of each row written since the last check

    def add(self, step: int, values: torch.Tensor) -> None:
        if self._rows is None or self._rows.device != values.device or self._rows.shape[1:] != values.shape:
            self.check()
            self._rows = torch.empty((self.ROWS, *values.shape), dtype=values.dtype, device=values.device)
        elif len(self._steps) == self.ROWS:
            self.check()
        self._rows[len(self._steps)].copy_(values)
        self._steps.append(step)

    def check(self) -> None:
        if not self._steps:
            return
        losses = self._rows[:len(self._steps), 0].tolist()
        steps, self._steps = self._steps, []
        for step, loss in zip(steps, losses):
            if not math.isfinite(loss):
                raise MCSplatError(f"step {step}: the loss became {loss}; lower the learning rates or the loss "
                                   f"terms' weights (--surface-*, --appearance-*, --*depth*), or check the input "
                                   f"images")


class StepPhases(Protocol):
    """Told where a step is: benchmarks/train_speed.py times the phases with it (the trainer passes none)."""

    def rendered(self, result: RenderResult) -> None:
        """After render(), before the loss."""
        ...

    def lap(self, phase: str) -> None:
        """The work since the previous mark was `phase`: other, render, loss, backward, strategy, reduce,
        optimizer."""
        ...


@dataclass
class Step:
    """What every step of a run shares: the model, its Adam, the strategy, the options, the scene's radius and
    background, the device; `reduce(model, [loss, psnr])` runs between the backward and the Adam step (with several
    processes it averages the gradients and the two values, distributed/team.py); each of `modules` sees the
    view's camera and render, in order, and takes its own step after the scene's; the loss is the sum of
    `loss_terms` (by default loss_terms.standard_terms: photometric, the strategy's, each module's); `phases`, when
    given, is told where each step is; `update` takes the optimizers' step around the render and after the backward
    (optim/update.py: the plain one, or on the CPU the projection's backward fused with Adam). The model's
    parameters and Adam's state change as the run goes (row surgery replaces them in place in `model.params` and the
    optimizers), never the objects themselves.

    A step reads nothing back from the device (a GPU's queue never waits for the host; docs/method.md says where that
    holds): the loss and PSNR stay there until a consumer reads them, and whether the loss stayed finite is read by
    `check_finite()`."""

    model: GaussianModel
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: Strategy
    config: TrainConfig
    scene_radius: float
    background: tuple[float, float, float] | torch.Tensor
    device: torch.device
    reduce: Reduce = alone
    modules: Sequence[PerImageModule] = ()
    loss_terms: Sequence[LossTerm] | None = None
    phases: StepPhases | None = None
    update: ParameterUpdate = field(default_factory=PlainUpdate)
    finite: FiniteLoss = field(default_factory=FiniteLoss, init=False)
    _backgrounds: dict = field(default_factory=dict, init=False, repr=False)  # by dtype, on the device: made once

    def on(self, model: GaussianModel, optimizers: dict, strategy: Strategy) -> Step:
        """The same step on another model, alone and without the run's modules and terms (--budget times throwaway
        copies of the run's model with it, leaving the run's own state as it is)."""
        return dataclasses.replace(self, model=model, optimizers=optimizers, strategy=strategy, reduce=alone,
                                   modules=(), loss_terms=None, phases=None)

    def __call__(self, step: int, view: View, plan: Plan, view_index: int = 0) -> StepResult:
        """Step `step` on training view `view` (index `view_index` of the scene's, for the per-image modules), as
        `plan` has it at this step (learning rates, resolution, SH degree; the strategy follows the plan's
        schedule)."""
        return self.run(step, view, plan, view_index, self.inputs(step, view, plan, view_index))

    def run(self, step: int, view: View, plan: Plan, view_index: int, inputs: StepInputs) -> StepResult:
        """The step with its view's inputs at hand (`inputs`)."""
        self.set_rates(step, plan)
        values, refine = self.work(step, view, plan, view_index, inputs, self.noise_lr(step, plan))
        self.finite.add(step, values)  # reduced: every process stops at the same step
        return StepResult(StepValues(values), refine)

    def set_rates(self, step: int, plan: Plan) -> None:
        """The position learning rate of `step` (it decays log-linearly over the run)."""
        set_means_lr(self.optimizers, means_lr_at(step, plan.steps, plan.optim, self.scene_radius))

    def inputs(self, step: int, view: View, plan: Plan, view_index: int) -> StepInputs:
        """What the step reads of its view: the camera at the step's resolution (coarse to fine, when configured),
        moved by the modules, and the photo and mask at its size, on the device."""
        camera = view.camera_at(plan.resolution_at(step)).to(self.device)
        for module in self.modules:
            camera = module.camera(view_index, camera)
        target = view.image_float(self.device, size=(camera.width, camera.height))
        keep = view.mask_float(self.device, size=(camera.width, camera.height))  # None unless the scene has masks
        return StepInputs(camera, target, keep)

    def terms(self) -> Sequence[LossTerm]:
        """The loss terms the step sums."""
        if self.loss_terms is not None:
            return self.loss_terms
        return standard_terms(self.config.ssim_weight, self.strategy, self.modules)

    def noise_lr(self, step: int, plan: Plan) -> float:
        """The learning rate the strategy's noise follows: the position learning rate after this step's decay, as
        gsplat has it (docs/method.md), or the schedule an ablation puts in its place (strategy/noise.py)."""
        return noise_lr_at(self.config.mcmc.noise_schedule, step + 1, plan.steps, plan.optim, self.scene_radius)

    def work(self, step: int, view: View, plan: Plan, view_index: int, inputs: StepInputs,
             noise_lr: float | torch.Tensor) -> tuple[torch.Tensor, RefineReport]:
        """The step's work on the device, from the render to the strategy's noise: ([loss, PSNR] reduced, what the
        strategy did). A step replayed as a CUDA graph (graphed_step.py) captures it with inputs in fixed places and
        the noise's rate as a tensor."""
        model, optimizers, strategy, modules = self.model, self.optimizers, self.strategy, self.modules
        lap = self.phases.lap if self.phases is not None else (lambda phase: None)
        camera, target, keep, terms = inputs.camera, inputs.target, inputs.keep, self.terms()
        lap("other")
        with self.update.rendering(model):  # the render's and the regularizers' gradients may be left to the update
            with render.pairs_sized_ahead():
                result = render.render(model, camera, self._background(model.means.dtype), plan.sh_degree_at(step),
                                       outputs=render_outputs(terms, step, plan.steps))
            lap("render")
            rgb = result.rgb
            for module in modules:
                rgb = module.apply(view_index, rgb)
            loss = total_loss(terms, StepContext(step, view, view_index, camera, rgb, target, keep, model, result,
                                                 plan.steps))
        lap("loss")
        if self.phases is not None:
            self.phases.rendered(result)
        loss.backward()
        lap("backward")
        strategy.step_post_backward(step, model, result, camera.width, camera.height)
        lap("strategy")
        values = self.reduce(model, torch.stack([loss.detach(), psnr_on_device(rgb, target)]))
        lap("reduce")
        self.update.step(optimizers)  # and the gradients dropped
        for module in modules:
            module.step(step, plan)
        lap("optimizer")
        refine = strategy.step_post_optimizer(step, model, optimizers, noise_lr)
        lap("strategy")
        return values, refine

    def _background(self, dtype: torch.dtype) -> torch.Tensor:
        """The background as a tensor on the device, made once (a step copies nothing to the GPU but its image)."""
        if dtype not in self._backgrounds:
            self._backgrounds[dtype] = torch.as_tensor(self.background, dtype=dtype, device=self.device).reshape(3)
        return self._backgrounds[dtype]

    def check_finite(self) -> None:
        """Stop the run (MCSplatError) if a loss since the first step was not a finite number."""
        self.finite.check()


def step_kernels(device: torch.device, appearance: str = "none") -> list:
    """Every Warp kernel a training step launches on `device` (compiled before the first step)."""
    return (render.training_kernels(device) + losses.training_kernels(device) + optim.training_kernels(device)
            + appearance_kernels(appearance) + strategy_kernels(device))
