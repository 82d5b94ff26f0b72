"""Depth supervision as loss terms: the rendered depth held to the SfM points each image saw, or to depth maps.

    sparse     --sparse-depth W: for each training view, the SfM points its image observed (COLMAP's tracks,
               data/sfm_tracks.py) projected with the step's camera; the rendered depth sampled bilinearly at their
               pixels against their z
    metric     --depth-loss metric: the depth map (data/attachments/depth.py; a sensor's, LiDAR's) against the
               rendered depth where the map has one
    relative   --depth-loss relative: a monocular model's depth, known up to scale and shift: the scale and shift
               that bring the map closest to the render (least squares, no gradient) make the target
    disparity  --depth-loss disparity: the same for inverse depth (what MiDaS and Depth Anything give): the map's
               scale and shift fitted to the render's 1/z, the target the inverse of the fitted map

Every term is the mean relative error |D - T| / T of the rendered depth D against its target depth T, so that a far
point does not outweigh a near one (a depth's noise grows with it) and a weight means the same in any scene's units.
D is render()'s expected depth, the alpha-weighted mean z (already divided by alpha: RenderResult.depth); it is
read only where alpha is at least MIN_ALPHA, for where the render is nearly empty its mean depth is of a few faint
Gaussians and its gradient grows as 1 / alpha. A term gives None for a view without its input (no map, no point in
front of the camera and inside the image). Each weight starts at a share of the run (--*-from) and goes linearly to
a share of itself (--*-final) at the end.

Metric depth maps are checked once at set-up against the scene (check_metric_scale): maps in other units than the
scene's (millimetres of a scene in metres) are refused with what to set.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal, Sequence

import torch
import torch.nn.functional as F

from ..camera import Camera
from ..data import Scene
from ..data.sfm_tracks import points_seen
from ..errors import MCSplatError
from ..option_checks import refuse_non_finite
from ..features import FeatureParts, FeatureStart
from ..loss_terms import StepContext

MIN_ALPHA = 0.5  # the render's depth is read where it is at least this opaque
MIN_PIXELS = 16  # a scale-and-shift fit needs this many pixels with both depths
SCALE_TOLERANCE = 10.0  # metric maps whose depths are this many times the scene's (or this share of them) are refused
CHECK_VIEWS, CHECK_POINTS = 16, 20_000  # what the scale check looks at: a few views, a sample of the Gaussians
DENSE_MODES = ("metric", "relative", "disparity")


@dataclass(frozen=True)
class Schedule:
    """A term's weight over the run: 0 before `start` (a share of the steps), then from `weight` linearly to
    `weight * final` at the last step."""

    weight: float
    start: float = 0.0
    final: float = 1.0

    def at(self, step: int, steps: int) -> float:
        begin = self.start * steps
        if self.weight == 0 or step < begin:
            return 0.0
        progress = min(1.0, (step - begin) / max(steps - 1 - begin, 1.0))
        return self.weight * (1.0 + (self.final - 1.0) * progress)


def relative_error(rendered: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """The weighted mean of |rendered - target| / target; 0, with a zero gradient, when no weight is positive. It
    reads nothing back from the device (a step's loss stays on it: docs/method.md)."""
    total = weights.sum()
    safe = torch.where(weights > 0, target, torch.ones_like(target))
    return (weights * (rendered - target).abs() / safe).sum() / torch.where(total > 0, total, torch.ones_like(total))


def sample_depth(depth: torch.Tensor, alpha: torch.Tensor, u: torch.Tensor, v: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """(expected depth, alpha) [k] at pixel positions (u, v) (centres at +0.5), bilinear in depth * alpha and in
    alpha: so that a point near an object's edge is not averaged with the zero depth of the empty pixels beside it."""
    weighted, opacity = sample_maps(torch.stack([depth * alpha, alpha]), u, v)
    return weighted / opacity.clamp_min(1e-10), opacity


def sample_maps(maps: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The maps [C, H, W] sampled bilinearly at pixel positions (u, v) (centres at +0.5): [C, k]."""
    height, width = maps.shape[-2:]
    grid = torch.stack([2 * u / width - 1, 2 * v / height - 1], dim=-1).to(maps.dtype)[None, None]
    return F.grid_sample(maps[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0]


def project(points: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(u, v, z) of the world points [k, 3] that lie in front of `camera` and inside its image (no gradient: a
    target, not something the loss moves)."""
    with torch.no_grad():
        local = camera.to_camera_space(points)
        u, v, inside = camera.pixels_of(local)
    return u[inside], v[inside], local[inside, 2]


class SparseDepth:
    """The rendered depth at the pixels of the SfM points each training view saw, against the points' depths."""

    def __init__(self, points: dict[str, torch.Tensor], schedule: Schedule):
        self.points, self.schedule = points, schedule

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        weight = self.schedule.at(ctx.step, ctx.steps)
        points = self.points.get(ctx.view.name)
        if weight == 0 or points is None:
            return None
        with torch.no_grad():  # every point, those outside the view weighing 0: no count to read back
            local = ctx.camera.to_camera_space(points)
            u, v, inside = ctx.camera.pixels_of(local)
        depth, alpha = sample_depth(ctx.result.depth, ctx.result.alpha, u, v)
        weights = (inside & (alpha >= MIN_ALPHA)).to(depth.dtype)
        if ctx.keep is not None:  # a point on pixels the mask leaves out says nothing, as the photo there does not
            weights = weights * sample_maps(ctx.keep.detach().permute(2, 0, 1), u, v)[0]
        return weight * relative_error(depth, local[:, 2], weights)


def fit_scale_shift(prior: torch.Tensor, target: torch.Tensor, weights: torch.Tensor
                    ) -> tuple[float, float] | None:
    """(s, t) minimising sum weights * (s prior + t - target)^2 (in float64, no gradient), or None when the pixels
    cannot fix both (fewer than MIN_PIXELS, or a flat prior)."""
    with torch.no_grad():
        w, m, d = (x.double().reshape(-1) for x in (weights, prior, target))
        if int((w > 0).sum()) < MIN_PIXELS:
            return None
        sw, sm, sd = w.sum(), (w * m).sum(), (w * d).sum()
        smm, smd = (w * m * m).sum(), (w * m * d).sum()
        determinant = sw * smm - sm * sm
        if not bool(determinant > 1e-12 * sw * smm):
            return None
        return float((sw * smd - sm * sd) / determinant), float((smm * sd - sm * smd) / determinant)


def target_depth(mode: str, prior: torch.Tensor, rendered: torch.Tensor, weights: torch.Tensor
                 ) -> torch.Tensor | None:
    """The depth the render is held to, from the map `prior` [H, W] (0: none) as `mode` reads it, 0 where there is
    none; None when a fit fails."""
    if mode == "metric":
        return prior
    fitted_to = rendered if mode == "relative" else 1.0 / rendered.clamp_min(1e-10)  # depth, or inverse depth
    fit = fit_scale_shift(prior, fitted_to.detach(), weights)
    if fit is None:
        return None
    scale, shift = fit
    if scale <= 0:  # nearer in the map is farther in the render: a map of the other kind (depth for disparity)
        # One message for every view and step (a warning is shown once per text): no number in it.
        other = "disparity" if mode == "relative" else "relative"
        warnings.warn(f"--depth-loss {mode}: a depth map fits the render only inverted; it is left out. Maps of "
                      f"{'disparity' if mode == 'relative' else 'depth'} want --depth-loss {other}", RuntimeWarning,
                      stacklevel=2)
        return None
    mapped = scale * prior + shift
    if mode == "disparity":
        mapped = torch.where(mapped > 0, 1.0 / mapped.clamp_min(1e-10), torch.zeros_like(mapped))
    return torch.where((prior > 0) & (mapped > 0), mapped, torch.zeros_like(mapped))


class DenseDepth:
    """The rendered depth against the view's depth map (metric, or up to scale and shift: relative, disparity)."""

    def __init__(self, mode: str, schedule: Schedule):
        if mode not in DENSE_MODES:
            raise ValueError(f"depth loss mode {mode!r} is not one of {DENSE_MODES}")
        self.mode, self.schedule = mode, schedule

    def __call__(self, ctx: StepContext) -> torch.Tensor | None:
        weight = self.schedule.at(ctx.step, ctx.steps)
        if weight == 0:
            return None
        prior = ctx.view.attachment("depth", ctx.target.device, (ctx.camera.width, ctx.camera.height))
        if prior is None:
            return None
        prior, rendered = prior[..., 0], ctx.result.depth
        weights = ((prior > 0) & (ctx.result.alpha.detach() >= MIN_ALPHA)).to(rendered.dtype)
        if ctx.keep is not None:
            weights = weights * ctx.keep[..., 0]
        target = target_depth(self.mode, prior, rendered, weights)
        if target is None:
            return None
        return weight * relative_error(rendered, target, weights * (target > 0))


def sparse_points(scene: Scene, device: torch.device | str) -> dict[str, torch.Tensor]:
    """{training view name: the SfM points [k, 3] its image saw} on `device`; refuses a scene without tracks."""
    seen = points_seen(scene.root) if scene.kind == "colmap" else None
    if seen is None:
        raise MCSplatError(f"--sparse-depth needs a COLMAP scene, whose model says which points each image saw; "
                           f"{scene.root} is a {scene.kind} scene (for depth maps: --depths with --depth-loss)")
    points = {view.name: torch.from_numpy(seen[view.name]).to(device, torch.float32)
              for view in scene.train if view.name in seen}
    if not points:
        raise MCSplatError(f"--sparse-depth: none of the {len(scene.train)} training views saw a point of the COLMAP "
                           f"model in {scene.root}; train without --sparse-depth")
    return points


def check_metric_scale(views: Sequence, means: torch.Tensor) -> None:
    """Refuse metric depth maps whose depths are not in the scene's units: the median of each map (over its known
    pixels) against the median z of the Gaussians `means` [N, 3] (the run's first, or its checkpoint's) inside the
    same view, over a few views; off by more than SCALE_TOLERANCE either way is one line saying what to set."""
    generator = torch.Generator().manual_seed(0)
    means = means.detach().float().cpu()
    if means.shape[0] > CHECK_POINTS:
        means = means[torch.randperm(means.shape[0], generator=generator)[:CHECK_POINTS]]
    ratios, maps, scene = [], [], []
    for view in [view for view in views if "depth" in view.attachments][:CHECK_VIEWS]:
        known = view.attachments["depth"].values
        known = known[known > 0]
        _, _, z = project(means, view.camera)
        if known.numel() and z.numel():
            maps.append(float(known.median()))
            scene.append(float(z.median()))
            ratios.append(maps[-1] / scene[-1])
    if not ratios:
        return
    ratio = float(torch.tensor(ratios).median())
    if 1 / SCALE_TOLERANCE <= ratio <= SCALE_TOLERANCE:
        return
    looks = "millimetres of a scene in metres" if 300 < ratio < 3000 else \
        "metres of a scene in millimetres" if 1 / 3000 < ratio < 1 / 300 else "in other units than the scene"
    raise MCSplatError(f"--depth-loss metric: the depth maps' depths are {ratio:.3g} times the scene's (median "
                       f"{float(torch.tensor(maps).median()):.3g} against {float(torch.tensor(scene).median()):.3g} "
                       f"scene units in the same views): they look like {looks}; set --depth-png-step to the scene "
                       f"units of a 16-bit PNG's step, save .npy maps in the scene's units, or use --depth-loss "
                       f"relative")


def depth_terms(scene: Scene, means: torch.Tensor, device: torch.device | str, *, sparse: Schedule,
                mode: str, dense: Schedule) -> list:
    """The depth terms the options ask for (sparse when its weight is positive, dense unless `mode` is "none"), in
    the order they are added after the standard ones; refuses what they cannot read."""
    terms: list = []
    if sparse.weight > 0:
        terms.append(SparseDepth(sparse_points(scene, device), sparse))
    if mode != "none":
        if not any("depth" in view.attachments for view in scene.train):
            raise MCSplatError(f"--depth-loss {mode}: none of the {len(scene.train)} training views has a depth map; "
                               f"give --depths auto (beside the photos, or the scene's depths/) or their folder")
        if mode == "metric":
            check_metric_scale(scene.train, means)
        terms.append(DenseDepth(mode, dense))
    return terms


@dataclass(frozen=True)
class DepthTermOptions:
    """Depth supervision (sparse depth from the SfM points; --depth-loss on the --depths maps)."""

    depth_loss: Literal["none", "metric", "relative", "disparity"] = "none"
    """Hold the rendered depth to the --depths maps: metric (a sensor's depths in the scene's units; maps in other
    units are refused), relative (a monocular model's depth, its scale and shift fitted to the render in each view)
    or disparity (the same for inverse depth: MiDaS, Depth Anything). The mean relative error where a map has a
    depth (docs/training.md)."""
    depth_weight: float = 0.1
    """Weight of --depth-loss (on the mean relative depth error) ..."""
    depth_from: float = 0.0
    """... from this share of the steps on ..."""
    depth_final: float = 1.0
    """... going linearly to this share of itself at the last step."""
    sparse_depth: float = 0.0
    """Weight of sparse depth from the SfM points (COLMAP scenes): the rendered depth at the pixel of each point an
    image saw held to the point's depth (mean relative error); 0: off. 0.1 is a start (docs/training.md) ..."""
    sparse_depth_from: float = 0.5
    """... from this share of the steps on (what the start costs: docs/training.md) ..."""
    sparse_depth_final: float = 0.0
    """... going linearly to this share of itself at the last step (0: fading out, so that the photos have the last
    steps to themselves; 1: held to the end, as the meshes of docs/outputs.md were measured, from the first step)."""

    def __post_init__(self) -> None:
        refuse_non_finite(self)
        if not (min(self.depth_weight, self.depth_final, self.sparse_depth, self.sparse_depth_final) >= 0
                and 0 <= self.depth_from <= 1 and 0 <= self.sparse_depth_from <= 1):
            raise MCSplatError("--depth-weight, --depth-final, --sparse-depth and --sparse-depth-final must be >= 0, "
                               "--depth-from and --sparse-depth-from within [0, 1]")

    def unused_options(self) -> tuple[str, ...]:
        return (("depth_weight", "depth_from", "depth_final") if self.depth_loss == "none" else ()) + \
            (("sparse_depth_from", "sparse_depth_final") if self.sparse_depth == 0 else ())

    unused_reason = ("these shape a depth term this run trains without (--depth-loss none, --sparse-depth 0), so "
                     "they would be ignored; add it, or leave them out")

    @property
    def sparse_schedule(self) -> Schedule:
        return Schedule(self.sparse_depth, self.sparse_depth_from, self.sparse_depth_final)

    @property
    def dense_schedule(self) -> Schedule:
        return Schedule(self.depth_weight, self.depth_from, self.depth_final)

    def setup(self, start: FeatureStart) -> FeatureParts:
        if self.sparse_depth == 0 and self.depth_loss == "none":
            return FeatureParts()
        return FeatureParts(loss_terms=depth_terms(start.scene, start.model.means, start.device, mode=self.depth_loss,
                                                   sparse=self.sparse_schedule, dense=self.dense_schedule))
