"""--surface: the loss terms that train Gaussians into a surface a mesh can be made of (PGSR's single-view terms).

    flatten          surface_flatten * mean over the Gaussians the step sees of their smallest scale / scene radius:
                     each Gaussian pulled toward a flat surface element, whose shortest axis is then its normal
    depth-normal     from --surface-from of the run on, surface_normal * mean over the pixels of
                     (1 - |image gradient|)^2 * |N(planar depth) - rendered normal|_1: the normal map
                     (render/outputs/normals.py) held to the normal of the depth of its own planes
                     (geometry/depth_normals.py), less at the photo's edges, where depth may jump
    distortion       from DISTORTION_FROM of the run on, surface_distortion * mean over the pixels of 2DGS's depth
                     distortion (render/outputs/distortion.py) times the scene radius squared: each pixel's Gaussians
                     pulled together in (inverse) depth, so that its weight sits on one surface, not in layers
    multi-view       from --surface-from of the run on, surface_multiview * the weighted mean distance, in pixels,
                     at which the step's pixels come back from a neighbouring view by the two planar depths (PGSR's
                     multi-view geometric consistency): a second render a step

All are loss terms (loss_terms.py) and work with either strategy. For MCMC nothing else changes: its position noise
is shaped by each Gaussian's covariance, so a flat Gaussian moves within its plane and hardly across it, and Eq. 9's
relocation scales all three axes by one factor, so a copy stays as flat as its source
(tests/training/test_surface_terms.py).
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Sequence

import torch

from . import render
from .data import View

from .errors import MCSplatError
from .option_checks import refuse_non_finite
from .features import FeatureParts, FeatureStart
from .geometry.depth_normals import normals_from_depth
from .geometry.reprojection import neighbours, round_trip_error
from .loss_terms import StepContext

NORMAL_EPS = 1e-6  # a rendered normal shorter than this (no Gaussian there) is left out
DISTORTION_FROM = 0.1  # 2DGS starts its distortion term at step 3,000 of 30,000, before the normal term
MULTIVIEW_THRESHOLD = 1.0  # pixels: a round trip that comes back farther is left out (PGSR's)


class Flatten:
    """The mean smallest scale of the Gaussians the step's view sees, in scene radii."""

    def __init__(self, weight: float, scene_radius: float):
        self.weight, self.scene_radius = weight, scene_radius

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        if self.weight == 0:
            return None
        seen = ctx.result.visible.to(ctx.model.means.dtype)  # dense: nothing waits to count the seen ones
        smallest = ctx.model.scales.min(dim=-1).values
        mean = (smallest * seen).sum() / seen.sum().clamp_min(1.0)  # 0 where the view sees none
        return self.weight * mean / self.scene_radius


def edge_weight(image: torch.Tensor) -> torch.Tensor:
    """[H, W] (1 - g)^2, g the grey image's gradient magnitude (central differences) over its largest: 1 where the
    photo is flat, 0 at its strongest edge."""
    grey = image.mean(dim=-1)
    across = torch.zeros_like(grey)
    down = torch.zeros_like(grey)
    across[:, 1:-1] = grey[:, 2:] - grey[:, :-2]
    down[1:-1, :] = grey[2:, :] - grey[:-2, :]
    gradient = torch.sqrt(across ** 2 + down ** 2)
    return (1.0 - gradient / gradient.max().clamp_min(1e-12)) ** 2


class DepthNormal:
    """The rendered normals against the normals of the planar depth, from a share of the run on."""

    def __init__(self, weight: float, start_share: float):
        self.weight, self.start_share = weight, start_share

    def active(self, step: int, steps: int) -> bool:
        return self.weight > 0 and step >= self.start_share * steps

    def render_outputs(self, step: int, steps: int) -> frozenset[str]:
        """The normal map and the planar depth, once the term is on (the two passes cost nothing before)."""
        return frozenset({"normals", "planar_depth"}) if self.active(step, steps) else frozenset()

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        if not self.active(ctx.step, ctx.steps):
            return None
        rendered = ctx.result.normal
        length = rendered.norm(dim=-1, keepdim=True)
        from_depth, valid = normals_from_depth(ctx.result.planar_depth, ctx.camera)
        valid = valid & (length[..., 0] > NORMAL_EPS)
        difference = (from_depth - rendered / length.clamp_min(NORMAL_EPS)).abs().sum(dim=-1)
        weight = edge_weight(ctx.target).detach() * valid
        return self.weight * (weight * difference).mean()


class Distortion:
    """2DGS's depth distortion, in the scene's radius (unitless), from a share of the run on."""

    def __init__(self, weight: float, scene_radius: float, start_share: float = DISTORTION_FROM):
        self.weight, self.scene_radius, self.start_share = weight, scene_radius, start_share

    def active(self, step: int, steps: int) -> bool:
        return self.weight > 0 and step >= self.start_share * steps

    def render_outputs(self, step: int, steps: int) -> frozenset[str]:
        return frozenset({"distortion"}) if self.active(step, steps) else frozenset()

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        if not self.active(ctx.step, ctx.steps):
            return None
        return self.weight * self.scene_radius ** 2 * ctx.result.distortion.mean()


class MultiView:
    """PGSR's multi-view geometric consistency, from a share of the run on: the step's planar depth and that of one
    of its view's neighbours (rendered here), each pixel sent to the neighbour and back (geometry/reprojection.py).
    The distance it comes back at is weighted by exp(-distance), as PGSR does, and left out beyond
    MULTIVIEW_THRESHOLD pixels (occluded there, or the two depths not yet near)."""

    def __init__(self, weight: float, start_share: float, views: Sequence[View]):
        self.weight, self.start_share, self.views = weight, start_share, list(views)
        self.neighbours = neighbours([view.camera for view in self.views]) if weight > 0 else []

    def active(self, step: int, steps: int) -> bool:
        return self.weight > 0 and step >= self.start_share * steps

    def render_outputs(self, step: int, steps: int) -> frozenset[str]:
        return frozenset({"normals", "planar_depth"}) if self.active(step, steps) else frozenset()

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        if not self.active(ctx.step, ctx.steps) or not self.neighbours[ctx.view_index]:
            return None
        # the neighbour drawn from the step's number: a resumed run draws the same ones
        other = self.views[random.Random(ctx.step).choice(self.neighbours[ctx.view_index])]
        camera = other.camera_at(ctx.camera.width / ctx.view.camera.width).to(ctx.model.means.device)
        background = torch.zeros(3, dtype=ctx.model.means.dtype, device=ctx.model.means.device)
        seen = render.render(ctx.model, camera, background, 0, outputs={"normals", "planar_depth"})
        error, valid = round_trip_error(ctx.result.planar_depth, ctx.camera, seen.planar_depth, camera)
        near = (valid & (error < MULTIVIEW_THRESHOLD)).to(error.dtype)
        weighted = torch.exp(-error).detach() * error * near
        return self.weight * weighted.sum() / near.sum().clamp_min(1.0)


def surface_terms(flatten: float, normal: float, start_share: float, scene_radius: float,
                  distortion: float = 0.0, multiview: float = 0.0, views: Sequence[View] = ()) -> list:
    """The --surface terms, in the order they are added after the standard ones (`views`: the scene's training
    views, the multi-view term's neighbours)."""
    return [Flatten(flatten, scene_radius), DepthNormal(normal, start_share), Distortion(distortion, scene_radius),
            MultiView(multiview, start_share, views)]


@dataclass(frozen=True)
class SurfaceOptions:
    """Training for a surface (the options of --surface)."""

    surface: bool = False
    """Train for a surface a mesh can be made of (PGSR's single-view terms): Gaussians flattened toward surface
    elements, and from --surface-from on, the rendered normals held to the normals of the rendered (planar) depth.
    Costs one more compositing pass a step while the second term is on."""
    surface_flatten: float = 100.0
    """Weight of the mean smallest scale of the Gaussians a step sees, in scene radii (PGSR's 100)."""
    surface_normal: float = 0.015
    """Weight of the depth-normal consistency term (PGSR's 0.015), weighted per pixel by (1 - image gradient)^2."""
    surface_from: float = 0.23
    """The share of the steps after which the depth-normal term starts (PGSR: step 7,000 of 30,000)."""
    surface_distortion: float = 0.0
    """Weight of 2DGS's depth distortion (a pixel's Gaussians pulled together in inverse depth, in scene radii),
    from a tenth of the run on; 0: off. Costs one more compositing pass a step while it is on."""
    surface_multiview: float = 0.0
    """Weight of PGSR's multi-view geometric consistency (PGSR: 0.03), from --surface-from on: each pixel sent to a
    neighbouring training view by the planar depth and back by that view's, the distance it comes back at held small.
    0: off. Costs a second render a step (the neighbour's) while it is on."""
    surface_mesh: bool = True
    """At the end of a --surface run, fuse its mesh into RUN/mesh.ply (as `mcsplat export RUN --format mesh` does,
    with that command's defaults), which the run's report then pictures; --no-surface-mesh leaves it to that
    command."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not (self.surface_flatten >= 0 and self.surface_normal >= 0 and self.surface_distortion >= 0
                and self.surface_multiview >= 0 and 0 <= self.surface_from <= 1):
            raise MCSplatError("--surface-flatten, --surface-normal, --surface-distortion and --surface-multiview "
                               "must be >= 0 and --surface-from within [0, 1]")

    def unused_options(self) -> tuple[str, ...]:
        return () if self.surface else ("surface_flatten", "surface_normal", "surface_from", "surface_distortion",
                                        "surface_multiview", "surface_mesh")

    unused_reason = ("the --surface-* options shape the loss terms of --surface and the mesh it ends with, which "
                     "this run trains without, so they would be ignored; add --surface, or leave them out")

    def setup(self, start: FeatureStart) -> FeatureParts:
        if not self.surface:
            return FeatureParts()
        return FeatureParts(loss_terms=surface_terms(self.surface_flatten, self.surface_normal, self.surface_from,
                                                     start.scene.radius, self.surface_distortion,
                                                     self.surface_multiview, start.scene.train))
