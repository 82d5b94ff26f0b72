"""Where a view vouches for empty space: in front of where its ray starts to meet the Gaussians, not in front of its
median depth.

A ray that crosses a semi-transparent surface (MCMC keeps many: docs/outputs.md, "Where MCMC's depth was lost")
reaches alpha 0.5 only behind it, so that view's median depth lies behind the surface, and the fusion would read
"empty" at the surface and carve a hole into it. The clear depth is where the ray's alpha reaches about CLEAR_ALPHA
instead: the median depth of the same Gaussians with each opacity o raised to 1 - (1 - o)^k,
k = log(0.5) / log(1 - CLEAR_ALPHA), whose transmittance is the k-th power of the original's where every Gaussian is
met at its peak. Off the peak it is a little higher, so the clear depth a little deeper, and the rasterizer's alpha
cut-offs and --antialiased's opacity compensation bend it a little more: a heuristic, not an exact level. The fusion
leaves a grid point between a view's clear depth and its median depth's band alone: the view saw something there and
cannot say what. On an opaque surface the two depths are the same. With `--depth planar` the clear depth is still
this median depth (at most the planar depth): on a box of flat discs it lies more than 3 voxels in front of the
planar depth on a few percent of the pixels, near the edges, and the mesh is as before.

The raised Gaussians are drawn in their base colour only (a depth needs no view-dependent colour).
"""

from __future__ import annotations

import math

import torch

from ..camera import Camera
from ..render import GaussiansLike, Splats, render
from ..render.constants import MEDIAN_TRANSMITTANCE
from .options import CLEAR_ALPHA


def raised_opacities(model: GaussiansLike, clear_alpha: float = CLEAR_ALPHA) -> Splats | None:
    """The Gaussians whose median depth is `model`'s clear depth; None where that is the median depth itself
    (`clear_alpha` at least the median's 0.5)."""
    if clear_alpha >= 1.0 - MEDIAN_TRANSMITTANCE:
        return None
    power = math.log(MEDIAN_TRANSMITTANCE) / math.log(1.0 - clear_alpha)
    return Splats(model.means, model.quats, model.scales, 1.0 - (1.0 - model.opacities) ** power,
                  model.sh[:, :1].contiguous(), getattr(model, "antialiased", False))


def clear_depth(raised: Splats | None, camera: Camera, depth: torch.Tensor) -> torch.Tensor | None:
    """[H, W]: the camera depth in front of which the view vouches for empty space, at most `depth` (the view's
    surface, -inf where it has none); None where that is `depth` itself (no `raised` Gaussians)."""
    if raised is None:
        return None
    met = render(raised, camera, None, 0, outputs={"median_depth"}).median_depth
    return torch.where(met > 0, torch.minimum(met, depth), depth)
