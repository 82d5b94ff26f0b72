"""The seam for per-image learned modules: something learned for each training image alongside the scene, which
changes how that image's view is rendered or compared (--appearance's colour transforms, --pose-opt's pose
corrections; next: an image's exposure, its rolling shutter).

A module is indexed by the training view's index in `scene.train`. In a step (step.Step) it may move the
camera before the render (`camera`), change the render before the loss (`apply`), add to the loss (`regularization`,
summed as one loss term: loss_terms.py) and, after the scene's Adam step, take its own (`step`). Its parameters are
its own business (the scene's optimisers never see them), and so is its checkpoint state: `state_dict` is saved under
the module's `key` in checkpoint.pt, and `load_state_dict` reads it back on --resume (None: the checkpoint was trained
without the module; it refuses with a line that says what to do).

Held-out views have no index here: a module learns what a training photo does differently from the scene, so test
views are rendered and scored with the scene alone (pose refinement leaves their poses as they are; run/evaluation.py's
compensated score fits its own colour transform to each test view's left half, for every run, appearance/heldout.py).
The scene and its exports never depend on a module.
"""

from __future__ import annotations

from typing import Protocol

import torch

from .camera import Camera


class PlanSteps(Protocol):
    """What a module sees of the run's plan (planning.Plan has it): its number of steps, for a schedule."""

    steps: int


class PerImageModule(Protocol):
    """One per-image learned module. Subclass it to take the identity defaults of what a module leaves alone."""

    key: str  # its entry in checkpoint.pt: stable, for checkpoints written earlier must still load

    def camera(self, index: int, camera: Camera) -> Camera:
        """Training view `index`'s camera as the module sees it (differentiable in its parameters); unchanged by
        default."""
        return camera

    def apply(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        """Training view `index`'s render [H, W, 3] as the loss should compare it; unchanged by default."""
        return rgb

    def regularization(self, index: int) -> torch.Tensor | None:
        """A scalar the loss adds for training view `index`, or None for nothing."""
        return None

    def step(self, step: int, plan: PlanSteps) -> None:
        """The module's optimiser step, after the scene's (then its gradients cleared)."""
        ...

    def state_dict(self) -> dict:
        ...

    def load_state_dict(self, state: dict | None) -> None:
        """Restore what `state_dict` saved; None (the checkpoint has no entry under `key`) raises an MCSplatError."""
        ...
