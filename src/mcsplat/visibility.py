"""Which Gaussians contribute nothing visible: composited into no pixel of any training view.

A Gaussian shows in a pixel only when its alpha (opacity x its 2D falloff) reaches 1/255 before the pixel's
transmittance runs out (the rasterizer's rule), so one of opacity below 1/255 is never seen, and neither is one that
lies outside every camera or behind opaque surfaces in all of them. `mcsplat train` counts them at the end of a run;
`mcsplat export --prune` leaves them out (docs/outputs.md, "Gaussians that show nowhere").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from tqdm import tqdm

from .data import View
from .gaussians import GaussianModel
from .render import render
from .render.constants import ALPHA_MIN


@dataclass(frozen=True)
class Invisible:
    total: int
    faint: int  # opacity below 1/255: invisible from any camera
    unseen: int  # composited into no pixel of any of the views (the faint ones included)

    def as_dict(self) -> dict[str, int]:
        """As metrics.json holds it."""
        return {"total": self.total, "opacity_below_1_255": self.faint, "never_composited": self.unseen}


def describe(counts: dict[str, int]) -> str:
    """One line on Invisible.as_dict()'s counts."""
    return (f"{counts['never_composited']:,} of {counts['total']:,} Gaussians contribute nothing visible (composited "
            f"into no pixel of any training view; {counts['opacity_below_1_255']:,} of them have opacity below 1/255)")


@torch.no_grad()
def seen_in(model: GaussianModel, views: Sequence[View], background, device: torch.device,
            progress: bool = False) -> torch.Tensor:
    """[N] bool: the Gaussian is composited into at least one pixel of one of `views` (colour plays no part)."""
    seen = torch.zeros(model.num_gaussians, dtype=torch.bool, device=device)
    for view in tqdm(views, desc="visibility", disable=not progress, leave=False):
        seen |= render(model, view.camera.to(device), background, 0).contributed.to(device)
    return seen


def count_invisible(model: GaussianModel, seen: torch.Tensor) -> Invisible:
    # alpha = opacity x a falloff of at most 1, so below ALPHA_MIN the rasterizer skips the Gaussian at every pixel
    faint = model.opacities.detach() < ALPHA_MIN
    return Invisible(total=model.num_gaussians, faint=int(faint.sum()), unseen=int((~seen).sum()))
