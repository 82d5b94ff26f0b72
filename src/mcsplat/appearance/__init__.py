"""Exposure and white-balance compensation: a colour transform per training image, learned with the scene.

Phone captures change exposure and white balance between frames; a scene fitted to every frame as it is bends its
colours (or grows floaters) to explain what is really the camera's doing. `--appearance affine` gives each training
image its own affine colour transform (affine.py), `--appearance bilateral-grid` a grid of them over the image and
its brightness (bilateral_grid.py). Either is applied to the render before the loss, with its own Adam and learning
rate (log-linear decay, as 3DGS's per-image exposure), a small pull toward identity, and the transforms' median
held at identity, so that a transform only explains how its photo departs from the typical one. The transforms are
not part of the scene: renders, the viewer and every export show the scene without them.

`Compensation` is what a training step sees of it: a per-image module (per_image.py) that changes the render and
adds its regularizer to the loss, saved under "appearance" in the checkpoint. Held-out views have no learned
transform; heldout.py has 3DGS's `train_test_exp` protocol for scoring them.
"""

from __future__ import annotations

import math

import torch

from ..compute.device import free_memory
from ..errors import MCSplatError
from ..per_image import PerImageModule, PlanSteps
from .affine import AffineAppearance
from .bilateral_grid import GRID_SHAPE, BilateralGridAppearance, grids_bytes
from .heldout import apply_transform, fitted_transform, split_halves

__all__ = ["MODES", "AffineAppearance", "BilateralGridAppearance", "Compensation", "apply_transform", "check_fits",
           "fitted_transform", "lr_at", "make_appearance", "split_halves", "training_kernels"]

MODES = ("none", AffineAppearance.MODE, BilateralGridAppearance.MODE)
MEMORY_SHARE = 0.5  # of the free memory the grids may take (the rest: the images, the model, the renders)
Transforms = AffineAppearance | BilateralGridAppearance


def make_appearance(mode: str, count: int, device: torch.device, pull_weight: float = 0.01,
                    tv_weight: float = 10.0, grid_shape: tuple[int, int, int] = GRID_SHAPE) -> Transforms | None:
    if mode == "affine":
        return AffineAppearance(count, device, pull_weight)
    if mode == "bilateral-grid":
        return BilateralGridAppearance(count, device, pull_weight, tv_weight, grid_shape)
    return None


def check_fits(mode: str, count: int, device: torch.device, grid_shape: tuple[int, int, int] = GRID_SHAPE) -> None:
    """A one-line error, before anything is allocated, when the bilateral grids of `count` training images would not
    fit in the memory free on `device` (a shape of 100000 100000 100 asked torch for 48 TB)."""
    if mode != BilateralGridAppearance.MODE:
        return
    need, free = grids_bytes(count, grid_shape), free_memory(device)
    if free is not None and need > MEMORY_SHARE * free:
        shape = " ".join(str(cells) for cells in grid_shape)
        raise MCSplatError(f"--appearance-grid-shape {shape}: the grids of the {count} training images need "
                           f"{need / 2**30:,.1f} GiB, more than {MEMORY_SHARE:.0%} of the {free / 2**30:.1f} GiB free "
                           f"on {device}; give a smaller --appearance-grid-shape (the default 16 16 8 takes "
                           f"{grids_bytes(count, GRID_SHAPE) / 2**20:,.0f} MB here)")


def training_kernels(mode: str, dtype: torch.dtype = torch.float32) -> list:
    """The Warp kernels a training step of this appearance mode launches."""
    from .slicing import slicing_kernels  # Warp: loaded when a run compiles its kernels, not as the CLI starts

    return slicing_kernels(dtype) if mode == "bilateral-grid" else []


def lr_at(step: int, steps: int, lr: float, lr_final: float) -> float:
    """Log-linear from lr at step 0 to lr_final at the last step."""
    t = min(max(step / max(steps, 1), 0.0), 1.0)
    return math.exp((1 - t) * math.log(lr) + t * math.log(lr_final))


def _set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr


class Compensation(PerImageModule):
    """What a training step needs of the appearance model: the transforms, their Adam and its schedule."""

    key = "appearance"

    def __init__(self, transforms: Transforms, lr: float, lr_final: float):
        self.transforms, self.lr, self.lr_final = transforms, lr, lr_final
        self.optimizer = transforms.optimizer(lr)

    def apply(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        return self.transforms(index, rgb)

    def regularization(self, index: int) -> torch.Tensor:
        return self.transforms.penalty(index)

    def step(self, step: int, plan: PlanSteps) -> None:
        """The Adam step of this training step (at its scheduled learning rate)."""
        _set_lr(self.optimizer, lr_at(step, plan.steps, self.lr, self.lr_final))
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.transforms.centre(step)

    def state_dict(self) -> dict:
        return {"mode": self.transforms.MODE, "transforms": self.transforms.state_dict(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict | None) -> None:
        mode = self.transforms.MODE
        if state is None or state.get("mode", "affine") != mode:  # checkpoints before bilateral grids: affine
            trained = "without it" if state is None else f"with --appearance {state.get('mode', 'affine')}"
            raise MCSplatError(f"--appearance {mode}: the checkpoint was trained {trained}; resume with the run's "
                               "own --appearance, or train a new run")
        self.transforms.load_state_dict(state["transforms"])
        self.optimizer.load_state_dict(state["optimizer"])
