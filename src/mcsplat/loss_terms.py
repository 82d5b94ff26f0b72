"""The training loss as a list of terms: the step (step.Step) sums what each term returns for the step's view.

A term is any callable taking the step's `StepContext` (the render, the photo, the mask, the model, ...) and
returning a scalar tensor, or None when it has nothing to add for that view. The standard loss is three kinds of
term, in this order (the order of the additions, so that a CPU run is bit for bit what it was):

    photometric            0.8 L1 + 0.2 D-SSIM over the pixels the view's mask keeps (losses.py)
    strategy               the strategy's regularizers (MCMC's opacity and scale L1; ADC's, zero by default)
    each module's          a per-image module's regularizer (per_image.py), e.g. --appearance's pull to identity

A new loss is one more term in the list that run/state.py's start makes (docs/extending.md, "A loss term"); the
step does not change (--surface's terms are in surface_terms.py, the depth priors' in depth_supervision/). A term
that reads an output the render gives only on request (the normal map, the median depth) names it in
`render_outputs`, render()'s keyword: the step asks for the union of its terms' outputs, so that a run whose terms
read none pays for none.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, Sequence

import torch

from .camera import Camera
from .data import View
from .gaussians import GaussianModel
from .losses import masked_photometric_loss
from .per_image import PerImageModule
from .render import RenderResult


@dataclass(frozen=True)
class StepContext:
    """What a loss term sees of one training step, after the render."""

    step: int
    view: View  # the training view (its attachments: view.attachment(kind, device, size))
    view_index: int  # its index in scene.train (the per-image modules' index)
    camera: Camera  # the camera rendered from (at the step's resolution, moved by the modules)
    rgb: torch.Tensor  # [H, W, 3] the render as the modules changed it
    target: torch.Tensor  # [H, W, 3] the photo at the render's size
    keep: torch.Tensor | None  # [H, W, 1] the mask's weights, None when the scene has no masks
    model: GaussianModel
    result: RenderResult  # the render itself: alpha, expected depth, ...
    steps: int = 0  # the run's planned steps (a term that starts part-way through reads it)


class LossTerm(Protocol):
    # Optionally: render_outputs, the outputs it reads from ctx.result, as a set (frozenset({"normals"})) or as a
    # method render_outputs(step, steps) giving the set for that step (empty while the term is off); and
    # graph_phase(step, steps), what its work branches on at that step, for a step replayed as a CUDA graph
    # (graph_phase below; a term that does not say keeps the step out of a graph).
    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        ...


def render_outputs(terms: Sequence[LossTerm], step: int = 0, steps: int = 0) -> frozenset[str]:
    """The outputs a render gives on request (render(outputs=...)) that the terms read at `step`: none for the
    standard loss."""
    wanted: set[str] = set()
    for term in terms:
        outputs = getattr(term, "render_outputs", ())
        wanted.update(outputs(step, steps) if callable(outputs) else outputs)
    return frozenset(wanted)


def graph_phase(terms: Sequence[LossTerm], step: int, steps: int) -> tuple | None:
    """What the terms' work branches on at `step`, each term's graph_phase(step, steps), for a step replayed as a
    CUDA graph (graphed_step.py): a graph is replayed only in the phase it was captured in. None when a term does not
    say (it may read the view's attachments, or weigh itself by the step: a graph would keep its first weight)."""
    phases = []
    for term in terms:
        said = getattr(term, "graph_phase", None)
        phase = said(step, steps) if said is not None else None
        if phase is None:
            return None
        phases.append(phase)
    return tuple(phases)


class Photometric:
    """(1 - ssim_weight) L1 + ssim_weight D-SSIM over the pixels the view's mask keeps."""

    def __init__(self, ssim_weight: float):
        self.ssim_weight = ssim_weight

    def __call__(self, ctx: StepContext) -> torch.Tensor:
        return masked_photometric_loss(ctx.rgb, ctx.target, ctx.keep, self.ssim_weight)

    def graph_phase(self, step: int, steps: int) -> tuple:
        return ()  # the same work at every step


class StrategyRegularization:
    """The strategy's regularizers (strategy.regularization(model))."""

    def __init__(self, strategy: Any):
        self.strategy = strategy

    def __call__(self, ctx: StepContext) -> torch.Tensor:
        return self.strategy.regularization(ctx.model)

    def graph_phase(self, step: int, steps: int) -> tuple:
        return ()  # fixed weights


class ModuleRegularization:
    """A per-image module's regularizer for the step's view."""

    def __init__(self, module: PerImageModule):
        self.module = module

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        return self.module.regularization(ctx.view_index)


def standard_terms(ssim_weight: float, strategy: Any, modules: Sequence[PerImageModule] = ()) -> list[LossTerm]:
    """The loss every run trains with: the photometric term, the strategy's, then each module's."""
    return [Photometric(ssim_weight), StrategyRegularization(strategy), *map(ModuleRegularization, modules)]


def total_loss(terms: Sequence[LossTerm], ctx: StepContext) -> torch.Tensor:
    """The sum of the terms, added left to right (the first must give a tensor: the photometric term does)."""
    loss = None
    for term in terms:
        value = term(ctx)
        if value is not None:
            loss = value if loss is None else loss + value
    if loss is None:
        raise ValueError("no loss term gave a value for this step")
    return loss
