"""--surface (surface_terms.py): its two loss terms, when they switch on, what MCMC's noise and relocation do to flat
Gaussians, and a short run that comes out flatter than without it."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from mcsplat.config import ModelConfig, TrainConfig, config_of
from mcsplat.gaussians import GaussianModel
from mcsplat.geometry.rotation import quaternion_to_rotation
from mcsplat.loss_terms import StepContext, render_outputs
from mcsplat.mesh import MeshOptions, read_mesh
from mcsplat.optim import OptimConfig, make_optimizers
from mcsplat.render import render
from mcsplat.run.trained import load
from mcsplat.strategy.mcmc import MCMCConfig, inject_noise, relocate_dead
from mcsplat.surface_terms import DISTORTION_FROM, DepthNormal, Distortion, Flatten, edge_weight, surface_terms
from mcsplat.train import train

from tests.render.test_render import make_camera
from tests.render.test_normals import flat_disk

REPO = Path(__file__).resolve().parents[2]


def flat_model(n: int, seed: int = 0, opacity: float = 0.3) -> GaussianModel:
    """Gaussians 100 times thinner along one random axis than along the other two, at random rotations."""
    g = torch.Generator().manual_seed(seed)
    scales = torch.full((n, 3), 0.1)
    scales[torch.arange(n), torch.randint(0, 3, (n,), generator=g)] = 0.001
    logit = math.log(opacity / (1 - opacity))
    return GaussianModel(means=torch.randn(n, 3, generator=g), log_scales=scales.log(),
                         quats=torch.randn(n, 4, generator=g), opacity_logits=torch.full((n,), logit),
                         sh0=torch.zeros(n, 1, 3), shN=torch.zeros(n, 15, 3))


def thin_axes(model: GaussianModel) -> torch.Tensor:
    """[N, 3] each Gaussian's thin axis in the world (a column of its rotation)."""
    rotation = quaternion_to_rotation(model.quats.detach())
    thin = model.scales.detach().argmin(dim=-1)
    return rotation[torch.arange(model.num_gaussians), :, thin]


def context(result, model, camera, target, step=0, steps=100) -> StepContext:
    return StepContext(step, None, 0, camera, result.rgb, target, None, model, result, steps)


def test_flatten_is_the_mean_smallest_scale_of_the_seen_gaussians_in_scene_radii():
    model = flat_model(40)
    camera = make_camera(45, 37)
    result = render(model, camera)
    value = Flatten(100.0, scene_radius=2.0)(context(result, model, camera, result.rgb.detach()))
    seen = result.visible
    assert 0 < int(seen.sum()) < 40, "some Gaussians outside the view: the term ignores them"
    torch.testing.assert_close(value, 100.0 * model.scales[seen].min(dim=-1).values.mean() / 2.0)
    value.backward()
    grads = model.params["log_scales"].grad
    assert (grads[~seen] == 0).all() and (grads[seen] != 0).sum() == int(seen.sum()), "one axis of each seen one"


def test_the_depth_normal_term_starts_at_its_share_and_asks_for_its_outputs_only_then():
    term = DepthNormal(0.015, start_share=0.25)
    assert render_outputs([term], step=24, steps=100) == frozenset()
    assert render_outputs([term], step=25, steps=100) == {"normals", "planar_depth"}
    model, camera = flat_model(10), make_camera(45, 37)
    result = render(model, camera)
    assert term(context(result, model, camera, result.rgb.detach(), step=10, steps=100)) is None


def test_the_depth_normal_term_is_zero_on_a_plane_and_positive_on_a_bumpy_scene():
    camera = make_camera(45, 37, dtype=torch.float64)
    term = DepthNormal(1.0, start_share=0.0)
    disk = flat_disk(35.0, radius=1.0)
    out = render(disk, camera, outputs={"normals", "planar_depth"})
    flat = term(context(out, disk, camera, torch.full((37, 45, 3), 0.5, dtype=torch.float64)))
    bumpy_model = flat_model(60, seed=4, opacity=0.8)
    bumpy_model = GaussianModel(**{k: v.detach().double() for k, v in bumpy_model.params.items()})
    bumpy_model.params["means"].data *= 0.3
    out = render(bumpy_model, camera, outputs={"normals", "planar_depth"})
    bumpy = term(context(out, bumpy_model, camera, torch.full((37, 45, 3), 0.5, dtype=torch.float64)))
    assert flat.item() < 1e-6 < 0.05 < bumpy.item()
    bumpy.backward()
    assert bumpy_model.params["quats"].grad.abs().max() > 0 and bumpy_model.params["means"].grad.abs().max() > 0


def test_the_distortion_term_starts_at_a_tenth_of_the_run_and_is_the_mean_map_in_scene_radii():
    term = Distortion(10.0, scene_radius=2.0)
    assert DISTORTION_FROM == 0.1 and render_outputs([term], step=9, steps=100) == frozenset()
    assert render_outputs([term], step=10, steps=100) == {"distortion"}
    assert render_outputs([Distortion(0.0, scene_radius=2.0)], step=50, steps=100) == frozenset()
    model, camera = flat_model(60, seed=2, opacity=0.6), make_camera(45, 37)
    model.params["means"].data *= 0.5
    out = render(model, camera, outputs={"distortion"})
    value = term(context(out, model, camera, out.rgb.detach(), step=10, steps=100))
    assert value.item() > 0
    torch.testing.assert_close(value, 10.0 * 4.0 * out.distortion.mean())
    value.backward()
    assert model.params["means"].grad.abs().max() > 0 and model.params["opacity_logits"].grad.abs().max() > 0
    assert term(context(out, model, camera, out.rgb.detach(), step=9, steps=100)) is None


def test_the_edge_weight_is_one_on_flat_photo_and_zero_at_its_strongest_edge():
    image = torch.zeros(20, 30, 3)
    image[:, 15:] = 1.0
    weight = edge_weight(image)
    assert weight[:, :10].eq(1).all() and weight[:, 20:].eq(1).all()
    assert weight[:, 14:16].eq(0).all()


def test_mcmc_noise_moves_a_flat_gaussian_within_its_plane():
    """The noise is shaped by the covariance: across a Gaussian 100 times thinner than it is wide, it moves 10^4
    times less than along it."""
    model = flat_model(2000, seed=1, opacity=0.001)  # nearly transparent: the opacity gate lets the noise through
    before = model.means.detach().clone()
    inject_noise(model, factor=1.0, generator=torch.Generator().manual_seed(2))
    moved = model.means.detach() - before
    across = (moved * thin_axes(model)).sum(dim=-1).abs()
    assert across.max() < 1e-3 * moved.norm(dim=-1).median()


def test_mcmc_relocation_keeps_a_flat_gaussian_flat():
    """Eq. 9 scales all three axes of a source and its copies by one factor: their shape, flat, is kept."""
    model = flat_model(200, seed=3, opacity=0.6)
    logits = model.params["opacity_logits"].detach()
    logits[:50] = -10.0  # dead
    optimizers = make_optimizers(model, OptimConfig(), 1.0)
    slots, sources = relocate_dead(model, optimizers, torch.Generator().manual_seed(0))
    assert len(slots) == 50

    def ratio(model, rows):
        scales = model.scales.detach()[rows]
        return scales.min(dim=-1).values / scales.max(dim=-1).values

    torch.testing.assert_close(ratio(model, slots), torch.full((50,), 0.01), rtol=1e-4, atol=0)
    torch.testing.assert_close(ratio(model, sources), torch.full((50,), 0.01), rtol=1e-4, atol=0)


def flatness(run: Path) -> float:
    """The median of smallest over largest scale of a trained run's Gaussians."""
    scales = load(run, torch.device("cpu")).model.scales.detach()
    return float((scales.min(dim=-1).values / scales.max(dim=-1).values).median())


def test_a_surface_run_comes_out_flatter(tmp_path, monkeypatch):
    import mcsplat.mesh

    # The run's mesh on a coarse volume (the default's 2^24 voxels take most of a minute here).
    monkeypatch.setattr(mcsplat.mesh, "MeshOptions", lambda: MeshOptions(voxel_budget=2**18))
    base = dict(data=REPO / "data" / "lego_demo", steps=60, quiet=True, lpips_net="alex", eval_every=0, save_every=0,
                save_renders=False, model=ModelConfig(num_init_points=1500), scale_schedule=False,
                mcmc=MCMCConfig(cap_max=1800, refine_start=20, refine_every=20))
    train(TrainConfig(out=tmp_path / "plain", **base))
    metrics = train(config_of(out=tmp_path / "surface", surface=True, surface_from=0.5, **base))
    # Adam moves a log-scale by at most its rate (0.005) a step: 60 steps can thin the smallest axis by about a
    # quarter, not more (the plain run stays near round: 0.95 here).
    assert flatness(tmp_path / "surface") < 0.9 * flatness(tmp_path / "plain")
    assert math.isfinite(metrics["psnr"])
    # The --surface run ends with its mesh, which its report pictures; the plain run with neither.
    assert len(read_mesh(tmp_path / "surface" / "mesh.ply").faces) > 1000
    assert "The mesh of mesh.ply" in (tmp_path / "surface" / "report.html").read_text()
    assert not (tmp_path / "plain" / "mesh.ply").exists()
    assert "The mesh of" not in (tmp_path / "plain" / "report.html").read_text()
    assert surface_terms(100.0, 0.015, 0.5, 1.0)[1].active(30, 60)


def test_a_surface_run_makes_its_mesh_unless_told_not_to(tmp_path):
    from mcsplat.subscribers import MeshWriter
    from mcsplat.train import standard_subscribers

    def writes_mesh(**options) -> bool:
        config = config_of(data=REPO / "data" / "lego_demo", quiet=True, **options)
        return any(isinstance(s, MeshWriter) for s in standard_subscribers(config, tmp_path))

    assert writes_mesh(surface=True) and not writes_mesh(surface=True, surface_mesh=False) and not writes_mesh()
