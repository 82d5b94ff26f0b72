"""MCMC's health at each refine step: the instruments that show a collapse coming (docs/method.md, "When the cap is
far above what the scene needs").

At each refine step the strategy reports, as levels of its RefineReport (log.jsonl keeps the last refine step's
values of each record; the report plots them):

    dead_share          the share of the Gaussians dead (opacity <= min_opacity) before relocation
    unseen_dead_share   the share of those dead that no view composited since the previous refine step: they had
                        no photometric gradient, only the regularizers', in that window
    copies_max          the most copies one host received at this refine step (relocation and growth together)
    copies_mean         the mean over the hosts that received any
    born_dead_share     the share of those copies whose Eq. 9 opacity is at or below min_opacity: dead when born
    unplaced            dead Gaussians that relocation left where they are, for want of a host that can give
                        copies that stay alive (relocation "alive"; always 0 with the paper's relocation)

`SeenWindow` keeps which Gaussians were composited since the last refine step, from each step's render.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["SeenWindow", "HEALTH_LEVELS", "refine_health"]

HEALTH_LEVELS = ("dead_share", "unseen_dead_share", "copies_max", "copies_mean", "born_dead_share", "unplaced")


class SeenWindow:
    """Which Gaussians any view composited since the last reset (one bool per Gaussian)."""

    def __init__(self) -> None:
        self.seen: torch.Tensor | None = None
        self.rendered = False  # whether a render was added since the last reset

    @torch.no_grad()
    def add(self, render_result: Any, num_gaussians: int) -> None:
        contributed = render_result.contributed
        if contributed.shape[0] != num_gaussians:
            raise ValueError(f"the render has {contributed.shape[0]} Gaussians but the model {num_gaussians}")
        if self.seen is None or self.seen.shape[0] != num_gaussians:
            self.seen = torch.zeros(num_gaussians, dtype=torch.bool, device=contributed.device)
        self.seen |= contributed
        self.rendered = True

    def reset(self) -> None:
        """Start a new window, in the same tensor (a step replayed as a CUDA graph adds to the one it captured)."""
        if self.seen is not None:
            self.seen.zero_()
        self.rendered = False

    def unseen_share(self, mask: torch.Tensor) -> float | None:
        """The share of the Gaussians in `mask` that no view composited in the window (None without a full window:
        the model's rows changed since the last reset, or nothing was rendered)."""
        if self.seen is None or not self.rendered or self.seen.shape != mask.shape:
            return None
        count = int(mask.sum())
        return float((mask & ~self.seen.to(mask.device)).sum()) / count if count else 0.0


def refine_health(num_before: int, dead: int, unseen_dead_share: float | None, sources: torch.Tensor,
                  born_opacities: torch.Tensor, min_opacity: float, unplaced: int) -> dict[str, float]:
    """The levels of one refine step. `sources`: every copy's host index (relocation and growth together);
    `born_opacities`: the Eq. 9 opacity each copy was given (before any clamp)."""
    levels: dict[str, float] = {"dead_share": round(dead / num_before, 4) if num_before else 0.0,
                                "unplaced": float(unplaced)}
    if unseen_dead_share is not None:
        levels["unseen_dead_share"] = round(unseen_dead_share, 4)
    if sources.numel():
        per_host = torch.bincount(sources)
        per_host = per_host[per_host > 0]
        levels["copies_max"] = float(per_host.max())
        levels["copies_mean"] = round(float(per_host.float().mean()), 3)
        levels["born_dead_share"] = round(float((born_opacities <= min_opacity).float().mean()), 4)
    return levels
