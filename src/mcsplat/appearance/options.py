"""--appearance's options, and what the feature adds to a run: the Compensation module (features.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ..errors import MCSplatError
from ..option_checks import refuse_non_finite
from ..features import FeatureParts, FeatureStart


@dataclass(frozen=True)
class AppearanceOptions:
    """Exposure and white-balance compensation."""

    appearance: Literal["none", "affine", "bilateral-grid"] = "none"
    """Exposure / white-balance compensation: 'affine' learns a colour transform (3x3 + bias) per training image,
    'bilateral-grid' a 16x16x8 grid of them over the image and its brightness; applied to the render before the
    loss; renders and exports show the scene without it. Evaluation adds the compensated score (an affine transform
    of each test view fitted on its left half, its right half scored)."""
    appearance_lr: float = 0.003
    """Learning rate of the per-image transforms at the first step (docs/imperfect-captures.md says why) ..."""
    appearance_lr_final: float = 0.0003
    """... decaying log-linearly to this at the last step."""
    appearance_reg: float = 0.01
    """Weight of the pull of each image's transform toward identity (squared distance of A from I and of b from 0;
    for a bilateral grid, of its mean transform)."""
    appearance_grid_shape: tuple[int, int, int] = (16, 16, 8)
    """A bilateral grid's cells across the image, down it and over brightness (gsplat's 16 16 8, made for photos of
    about a megapixel: a grid holds 12 numbers a cell, so small images want a coarser one)."""
    appearance_grid_tv: float = 10.0
    """Weight of a bilateral grid's total variation (mean squared difference of neighbouring cells; gsplat's 10)."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not (self.appearance_lr > 0 and self.appearance_lr_final > 0 and self.appearance_reg >= 0
                and self.appearance_grid_tv >= 0):
            raise MCSplatError("--appearance-lr and --appearance-lr-final must be positive, --appearance-reg and "
                               "--appearance-grid-tv 0 or more")
        if min(self.appearance_grid_shape) < 2:
            raise MCSplatError("--appearance-grid-shape needs at least 2 cells along each of its three axes")

    def check_processes(self, world_size: int) -> None:
        if self.appearance != "none" and world_size > 1:
            raise MCSplatError("--appearance does not work with several training processes yet (each holds the "
                               "transforms of its own views); train in one process, or leave it out")

    def setup(self, start: FeatureStart) -> FeatureParts:
        from . import Compensation, check_fits, make_appearance  # the transforms' kernels: when a run starts

        if self.appearance == "none":
            return FeatureParts()
        images = len(start.scene.train)
        check_fits(self.appearance, images, start.device, self.appearance_grid_shape)  # before the grids are made
        transforms = make_appearance(self.appearance, images, start.device, self.appearance_reg,
                                     self.appearance_grid_tv, self.appearance_grid_shape)
        return FeatureParts(modules=[Compensation(transforms, self.appearance_lr, self.appearance_lr_final)])
