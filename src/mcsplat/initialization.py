"""The Gaussians a run starts from: one per SfM point of the scene, or random points (the paper's default)."""

from __future__ import annotations

import torch

from .config import TrainConfig
from .data import Scene
from .data.scene import OBJECT_CENTRIC_KINDS
from .errors import MCSplatError
from .gaussians import GaussianModel


def initial_model(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator
                  ) -> tuple[GaussianModel, str]:
    """(model, a note saying which initialisation was used) for `--model.init auto|sfm|random`.

    auto takes the SfM points when the scene has them (never for Blender scenes, as the official code) and random
    points otherwise: a cube of +-init_extent scene radii around the world origin, or Blender's [-1.3, 1.3]^3 and the
    unit sphere's cube for object-centric scenes."""
    m = config.model
    use_sfm = m.init == "sfm" or (m.init == "auto" and scene.points is not None and scene.kind != "blender")
    if use_sfm:
        if scene.points is None:
            raise MCSplatError(f"--model.init sfm: {scene.root} has no SfM points; use --model.init random")
        model = GaussianModel.from_points(scene.points, scene.point_colors, init_scale=m.init_scale,
                                          init_opacity=m.init_opacity, sh_degree=m.sh_degree, device=device)
        return within_cap(model, "SfM", cap_of(config), generator)
    model = GaussianModel.random_init(scene.radius, blender=scene.kind in OBJECT_CENTRIC_KINDS,
                                      num_points=m.num_init_points,
                                      extent=m.init_extent, init_scale=m.init_scale, init_opacity=m.init_opacity,
                                      sh_degree=m.sh_degree, generator=generator, device=device)
    return within_cap(model, "random", cap_of(config), generator)


def cap_of(config: TrainConfig) -> int | None:
    """The most Gaussians the run may hold (MCMC's cap, ADC's optional budget)."""
    return config.mcmc.cap_max if config.strategy == "mcmc" else config.adc.cap_max


def within_cap(model: GaussianModel, kind: str, cap: int | None, generator: torch.Generator
               ) -> tuple[GaussianModel, str]:
    """(the model, or a random `cap` of its Gaussians when it has more; the note saying which). Without this a run
    would train above its cap until the first refine step (gsplat issue 516)."""
    n = model.num_gaussians
    if cap is None or n <= cap:
        return model, f"{kind} ({n:,} points)"
    keep = torch.randperm(n, generator=generator, device=generator.device)[:cap].sort().values
    return model.subset(keep), f"{kind} ({n:,} points, {cap:,} of them kept at random to stay within --cap-max)"
