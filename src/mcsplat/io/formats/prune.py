"""Which Gaussians to export: drop the near-transparent ones and optionally keep only the N that contribute most.

An MCMC run at its cap carries many Gaussians of almost zero opacity (they wait to be relocated); they cost file
size and viewer time for nothing (gsplat #822).
"""

from __future__ import annotations

import numpy as np

from ...errors import MCSplatError


def opacities(params: dict[str, np.ndarray]) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-params["opacity_logits"].astype(np.float64)))


def contribution(params: dict[str, np.ndarray]) -> np.ndarray:
    """A Gaussian's weight in the images: opacity times the area of its largest cross-section (the product of its
    two largest scales), the footprint it covers from most directions."""
    scales = np.sort(np.exp(params["log_scales"].astype(np.float64)), axis=1)
    return opacities(params) * scales[:, 1] * scales[:, 2]


def select_gaussians(params: dict[str, np.ndarray], min_opacity: float = 0.0, max_gaussians: int | None = None
                     ) -> np.ndarray:
    """Indices (ascending) of the Gaussians with opacity > min_opacity, at most `max_gaussians` of them: those of
    largest contribution()."""
    if not 0.0 <= min_opacity < 1.0:
        raise MCSplatError(f"--min-opacity {min_opacity}: must be in [0, 1)")
    if max_gaussians is not None and max_gaussians < 1:
        raise MCSplatError(f"--max-gaussians {max_gaussians}: must be at least 1")
    keep = np.flatnonzero(opacities(params) > min_opacity)
    if max_gaussians is not None and keep.size > max_gaussians:
        score = contribution(params)[keep]
        keep = np.sort(keep[np.argsort(-score, kind="stable")[:max_gaussians]])
    return keep
