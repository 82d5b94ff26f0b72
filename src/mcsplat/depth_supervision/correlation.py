"""--depth-correlation: a monocular depth prior as a loss term, FSGS's and SparseGS's form of it.

    loss = weight * (1 - r)      r: Pearson's correlation of the rendered depth with the view's depth map

over the pixels where the map has a depth and the render is opaque (alpha at least terms.MIN_ALPHA), from
--depth-correlation-from of the run on. A correlation does not change when either depth is scaled or shifted, so
the map may be a monocular model's (any scale, any shift) without the fit per view that --depth-loss relative makes;
it holds the shape of the depth, not its values. A disparity map (MiDaS, Depth Anything) correlates negatively with
depth: give its inverse, or --depth-loss disparity.

It is the worked example of docs/extending.md ("A feature"): its options are a group of TrainConfig, declared here
with their help, and `setup` hands the run its loss term (features.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .terms import MIN_ALPHA
from ..errors import MCSplatError
from ..features import FeatureParts, FeatureStart
from ..loss_terms import StepContext
from ..option_checks import refuse_non_finite

MIN_PIXELS = 16  # a correlation over fewer pixels says little


def correlation_loss(rendered: torch.Tensor, prior: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """1 - Pearson's r of `rendered` with `prior` over the pixels where `keep` is True (0 when one is an increasing
    affine function of the other, 2 when a decreasing one); 0, with a zero gradient, over fewer than MIN_PIXELS pixels
    or where either is constant. It reads nothing back from the device (no count, no check on the host)."""
    kept = keep.to(rendered.dtype)
    count = kept.sum()
    per_pixel = torch.where(count > 0, count, torch.ones_like(count))
    x = (rendered - (rendered * kept).sum() / per_pixel) * kept
    y = (prior - (prior * kept).sum() / per_pixel) * kept
    spread = (x * x).sum() * (y * y).sum()
    says = (count >= MIN_PIXELS) & (spread > 0)
    r = (x * y).sum() / torch.where(says, spread, torch.ones_like(spread)).sqrt()
    return torch.where(says, 1.0 - r, torch.zeros_like(r))


class DepthCorrelation:
    """The loss term: the rendered depth's correlation with the view's depth map, from a share of the run on."""

    def __init__(self, weight: float, start_share: float):
        self.weight, self.start_share = weight, start_share

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        if ctx.step < self.start_share * ctx.steps:
            return None
        prior = ctx.view.attachment("depth", ctx.target.device, (ctx.camera.width, ctx.camera.height))
        if prior is None:  # a view without a map
            return None
        prior = prior[..., 0]
        keep = (prior > 0) & (ctx.result.alpha.detach() >= MIN_ALPHA)
        if ctx.keep is not None:  # the training mask
            keep = keep & (ctx.keep[..., 0] > 0)
        return self.weight * correlation_loss(ctx.result.depth, prior, keep)


@dataclass(frozen=True)
class DepthCorrelationOptions:
    """A monocular depth prior (the --depths maps, any scale and shift)."""

    depth_correlation: float = 0.0
    """Weight of 1 - the Pearson correlation of the rendered depth with the view's --depths map (FSGS, SparseGS),
    which ignores the map's scale and shift: a monocular model's depth as it is; 0: off ..."""
    depth_correlation_from: float = 0.0
    """... from this share of the steps on."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not (self.depth_correlation >= 0 and 0 <= self.depth_correlation_from <= 1):
            raise MCSplatError("--depth-correlation must be >= 0 and --depth-correlation-from within [0, 1]")

    def unused_options(self) -> tuple[str, ...]:
        return ("depth_correlation_from",) if self.depth_correlation == 0 else ()

    unused_reason = "it shapes --depth-correlation, which is 0 (off), so it would be ignored; give both, or neither"

    def setup(self, start: FeatureStart) -> FeatureParts:
        if self.depth_correlation == 0:
            return FeatureParts()
        if not any("depth" in view.attachments for view in start.scene.train):
            raise MCSplatError(f"--depth-correlation: none of the {len(start.scene.train)} training views has a depth "
                               f"map; give --depths auto (beside the photos, or the scene's depths/) or their folder")
        return FeatureParts(loss_terms=[DepthCorrelation(self.depth_correlation, self.depth_correlation_from)])
