"""The Gaussians a run starts from, and a line saying which and why.

`--model.init auto` (the default) takes, in this order:
- the scene's SfM points (COLMAP, LLFF with sparse/);
- for a synthetic object on a transparent background (NeRF-Synthetic: images with alpha), random points in a cube,
  as the official code does for those scenes;
- for a real capture with poses but no points (transforms.json, LLFF without sparse/, IDR), points triangulated
  from its known poses (capture/triangulate.py, cached), and where that fails, random points inside the training
  cameras' frustums (frustum.py).
`sfm`, `triangulate`, `frustum` and `random` force one of them; `random` is the paper's "Ours (Random)": a cube of
+-init_extent scene radii around the world origin ([-1.3, 1.3]^3 for object-centric scenes).
"""

from __future__ import annotations

import torch

from ..capture.triangulate import triangulated_points
from ..config import TrainConfig
from ..data import Scene
from ..errors import MCSplatError
from ..gaussians import GaussianModel
from .frustum import points_in_frustums

MIN_TRIANGULATION_VIEWS = 2  # a point is seen from two cameras at least


def initial_model(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator,
                  progress: bool = False) -> tuple[GaussianModel, str]:
    """(model, a note saying which initialisation was used and why), within the run's cap: a random subset of
    the points when there are more (gsplat issue 516: a run would otherwise train above its cap until its first
    refine step)."""
    model, note = _initial_model(config, scene, device, generator, progress)
    return within_cap(model, note, config.max_gaussians, generator)


def within_cap(model: GaussianModel, note: str, cap: int | None, generator: torch.Generator
               ) -> tuple[GaussianModel, str]:
    """(the model, or a random `cap` of its Gaussians when it has more; the note, saying so)."""
    n = model.num_gaussians
    if cap is None or n <= cap:
        return model, note
    keep = torch.randperm(n, generator=generator, device=generator.device)[:cap].sort().values
    return model.subset(keep), f"{note}; {cap:,} of the {n:,} kept at random to stay within --cap-max"


def _initial_model(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator,
                   progress: bool) -> tuple[GaussianModel, str]:
    m = config.model
    method = m.init
    if method == "auto":
        method = "sfm" if scene.points is not None else "random" if scene.alpha else "triangulate"
    if method == "sfm":
        if scene.points is None:
            raise MCSplatError(f"--model.init sfm: {scene.root} has no SfM points; use --model.init auto "
                               "(triangulated from the poses) or random")
        return _from_points(config, scene.points, scene.point_colors, device), \
            f"the scene's SfM points ({scene.points.shape[0]:,})"
    if method == "triangulate":
        try:
            found = _triangulated(config, scene, progress)
        except MCSplatError as error:
            if m.init != "auto":
                raise
            model = _in_frustums(config, scene, device, generator)
            return model, (f"random points in the cameras' frustums ({model.num_gaussians:,}): the scene has no SfM "
                           f"points and {error}")
        model = _from_points(config, torch.from_numpy(found.xyz), torch.from_numpy(found.rgb) / 255.0, device)
        how = "from the cache" if found.cached else f"in {found.seconds:.0f} s"
        return model, (f"{model.num_gaussians:,} points triangulated from the known poses of {found.views} views "
                       f"({how}; mean reprojection error {found.reprojection_error:.2f} px): the scene has no SfM "
                       "points")
    if method == "frustum":
        model = _in_frustums(config, scene, device, generator)
        return model, f"random points in the cameras' frustums ({model.num_gaussians:,})"
    model = GaussianModel.random_init(scene.radius, blender=scene.object_centric, num_points=m.num_init_points,
                                      extent=m.init_extent, init_scale=m.init_scale, init_opacity=m.init_opacity,
                                      sh_degree=m.sh_degree, generator=generator, device=device)
    why = ", a synthetic scene, as the official code" if m.init == "auto" else ""
    return model, f"random ({model.num_gaussians:,} points{why})"


def _triangulated(config: TrainConfig, scene: Scene, progress: bool):
    """The points triangulated from the training views' known poses; MCSplatError (one line) when they are too few
    to triangulate from."""
    if len(scene.train) < MIN_TRIANGULATION_VIEWS:
        raise MCSplatError(f"points from known poses need at least {MIN_TRIANGULATION_VIEWS} training views, and "
                           f"{scene.root} has {len(scene.train)} (--model.init frustum or random start without them)")
    return triangulated_points(scene.train, threads=config.threads, progress=progress)


def start_without_points(scene: Scene) -> str:
    """What `mcsplat train` (--model.init auto) starts a scene without SfM points from, in words (for `info`)."""
    if scene.alpha:
        return "`mcsplat train` starts from random points in a cube (a synthetic scene, as the official code does)"
    if len(scene.train) < MIN_TRIANGULATION_VIEWS:
        return (f"`mcsplat train` fills the cameras' frustums with random points (triangulating needs at least "
                f"{MIN_TRIANGULATION_VIEWS} training views)")
    return ("`mcsplat train` triangulates them from the known poses of the training views (cached after the first "
            "run), or fills the cameras' frustums with random points where that fails")


def _from_points(config: TrainConfig, points: torch.Tensor, colors: torch.Tensor, device: torch.device
                 ) -> GaussianModel:
    m = config.model
    return GaussianModel.from_points(points.float(), colors.float(), init_scale=m.init_scale,
                                     init_opacity=m.init_opacity, sh_degree=m.sh_degree, device=device)


def _in_frustums(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator
                 ) -> GaussianModel:
    cpu = torch.Generator().manual_seed(int(torch.randint(2**31, (1,), generator=generator, device=generator.device)))
    points, colors = points_in_frustums(scene.train, scene.radius, config.model.num_init_points, cpu)
    return _from_points(config, points, colors, device)
