"""GaussianModel: parameter layout, activations, random / SfM initialization, state round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mcsplat.gaussians import PARAM_KEYS, GaussianModel, knn_init_scales
from mcsplat.geometry.rotation import quaternion_to_rotation
from mcsplat.geometry.sh import SH_C0


def brute_force_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    d2 = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    nearest = np.sort(d2, axis=1)[:, :k]
    return np.sqrt(np.maximum(nearest.mean(axis=1), 1e-7))


def test_random_init_real_scene_matches_the_official_recipe():
    radius = 2.5
    g = torch.Generator().manual_seed(0)
    model = GaussianModel.random_init(radius, blender=False, num_points=4000, generator=g)
    n = model.num_gaussians
    assert n == 4000 and len(model) == 4000
    shapes = {k: tuple(v.shape) for k, v in model.params.items()}
    assert shapes == {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "opacity_logits": (n,),
                      "sh0": (n, 1, 3), "shN": (n, 15, 3)}
    means = model.means.detach()
    # Uniform in [-3R, 3R]^3 around the world origin: bounds, and the mean and variance of a uniform.
    assert means.abs().max() <= 3 * radius
    assert means.abs().max() > 0.99 * 3 * radius
    torch.testing.assert_close(means.mean(0), torch.zeros(3), atol=0.25, rtol=0)
    torch.testing.assert_close(means.var(0), torch.full((3,), (6 * radius) ** 2 / 12), rtol=0.06, atol=0)
    # Opacity 0.5, identity rotation, higher SH zero, near-grey DC in [0, 1/255].
    torch.testing.assert_close(model.opacities.detach(), torch.full((n,), 0.5))
    assert torch.equal(model.quats.detach(), torch.tensor([1.0, 0, 0, 0]).expand(n, 4))
    assert torch.count_nonzero(model.params["shN"]) == 0
    sh0 = model.params["sh0"].detach()
    assert sh0.min() >= 0 and sh0.max() <= 1 / 255
    colours = sh0[:, 0] * SH_C0 + 0.5
    assert (colours - 0.5).abs().max() < 0.0012
    # Isotropic scale 0.1 x sqrt(mean squared distance to the 3 nearest neighbours).
    expected = 0.1 * brute_force_scales(means.double().numpy())
    scales = model.scales.detach()
    assert torch.equal(scales[:, 0], scales[:, 1]) and torch.equal(scales[:, 0], scales[:, 2])
    np.testing.assert_allclose(scales[:, 0].numpy(), expected, rtol=1e-5)


def test_random_init_blender_cube_and_generator_reproducibility():
    a = GaussianModel.random_init(123.0, blender=True, num_points=500, generator=torch.Generator().manual_seed(3))
    b = GaussianModel.random_init(123.0, blender=True, num_points=500, generator=torch.Generator().manual_seed(3))
    c = GaussianModel.random_init(123.0, blender=True, num_points=500, generator=torch.Generator().manual_seed(4))
    assert a.means.abs().max() <= 1.3 and a.means.abs().max() > 1.2  # the radius is ignored for Blender
    for key in PARAM_KEYS:
        assert torch.equal(a.params[key], b.params[key])
    assert not torch.equal(a.means, c.means)


def test_random_init_default_is_100k_points_and_options_apply():
    model = GaussianModel.random_init(1.0, blender=False, generator=torch.Generator().manual_seed(0))
    assert model.num_gaussians == 100_000
    small = GaussianModel.random_init(1.0, blender=False, num_points=300, init_scale=1.0, init_opacity=0.1,
                                      sh_degree=1, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(small.opacities.detach(), torch.full((300,), 0.1))
    assert small.params["shN"].shape == (300, 3, 3) and small.sh.shape == (300, 4, 3) and small.sh_degree == 1
    np.testing.assert_allclose(small.scales[:, 0].detach().numpy(),
                               brute_force_scales(small.means.detach().double().numpy()), rtol=1e-5)


def test_from_points_keeps_positions_and_colours():
    g = torch.Generator().manual_seed(1)
    points = torch.randn(200, 3, generator=g)
    colours = torch.rand(200, 3, generator=g)
    model = GaussianModel.from_points(points, colours, init_scale=0.1, init_opacity=0.5)
    assert torch.equal(model.means.detach(), points)
    torch.testing.assert_close(model.sh[:, 0].detach() * SH_C0 + 0.5, colours, atol=1e-6, rtol=0)
    torch.testing.assert_close(model.opacities.detach(), torch.full((200,), 0.5))
    np.testing.assert_allclose(model.scales[:, 0].detach().numpy(),
                               0.1 * brute_force_scales(points.double().numpy()), rtol=1e-5)
    # numpy input works the same
    same = GaussianModel.from_points(points.numpy(), colours.numpy())
    assert torch.equal(same.params["sh0"], model.params["sh0"])


def test_knn_scales_edge_cases():
    assert knn_init_scales(np.zeros((1, 3))).tolist() == [1.0]
    two = knn_init_scales(np.array([[0.0, 0, 0], [3.0, 4.0, 0]]))
    np.testing.assert_allclose(two, [5.0, 5.0])
    duplicates = knn_init_scales(np.zeros((5, 3)))
    np.testing.assert_allclose(duplicates, math.sqrt(1e-7))  # floored, finite log


def test_activations_and_covariance():
    g = torch.Generator().manual_seed(2)
    model = GaussianModel.empty(50)
    with torch.no_grad():
        for key in PARAM_KEYS:
            model.params[key].copy_(torch.randn(model.params[key].shape, generator=g))
    torch.testing.assert_close(model.scales, torch.exp(model.params["log_scales"]))
    torch.testing.assert_close(model.opacities, torch.sigmoid(model.params["opacity_logits"]))
    assert model.sh.shape == (50, 16, 3)
    assert torch.equal(model.sh[:, :1], model.params["sh0"]) and torch.equal(model.sh[:, 1:], model.params["shN"])
    assert model.quats is model.params["quats"]
    # Sigma = R diag(s^2) R^T, symmetric positive definite with eigenvalues s^2.
    rot = quaternion_to_rotation(model.quats.detach())
    s = model.scales.detach()
    expected = rot @ torch.diag_embed(s ** 2) @ rot.transpose(1, 2)
    cov = model.covariances().detach()
    torch.testing.assert_close(cov, expected, rtol=1e-5, atol=1e-6)
    eig = torch.linalg.eigvalsh(cov.double())
    torch.testing.assert_close(eig, torch.sort(s.double() ** 2, dim=1).values, rtol=1e-4, atol=1e-7)


def test_state_dict_round_trip_into_a_model_of_another_size():
    source = GaussianModel.random_init(1.0, blender=False, num_points=77, sh_degree=2,
                                       generator=torch.Generator().manual_seed(5))
    state = source.state_dict()
    loaded = GaussianModel.from_state_dict(state)
    assert loaded.num_gaussians == 77 and loaded.sh_degree == 2
    into_existing = GaussianModel.empty(10)
    into_existing.load_state_dict(state)
    for key in PARAM_KEYS:
        assert torch.equal(loaded.params[key], source.params[key])
        assert torch.equal(into_existing.params[key], source.params[key])
        assert loaded.params[key].requires_grad

    class Holder(torch.nn.Module):  # nested in another module, the resize still happens
        def __init__(self):
            super().__init__()
            self.gaussians = GaussianModel.empty(3)

    holder = Holder()
    holder.load_state_dict({f"gaussians.{k}": v for k, v in state.items()})
    assert holder.gaussians.num_gaussians == 77
    with pytest.raises(RuntimeError, match="Missing"):
        GaussianModel.empty(2).load_state_dict({"params.means": state["params.means"]})


def test_render_reads_the_model():
    from mcsplat.camera import Camera, intrinsics
    from mcsplat.render import render

    model = GaussianModel.from_points(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[0.2, 0.4, 0.6]]),
                                      init_opacity=0.5)
    with torch.no_grad():
        model.params["log_scales"].fill_(math.log(0.3))
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    camera = Camera(K=intrinsics(40.0, 40.0, 16.5, 16.5), world_to_camera=w2c, width=32, height=32)
    result = render(model, camera)
    # The centre pixel of a single Gaussian over black: opacity x colour.
    torch.testing.assert_close(result.rgb[16, 16], 0.5 * torch.tensor([0.2, 0.4, 0.6]), atol=1e-6, rtol=0)
    result.rgb.sum().backward()
    assert model.params["means"].grad is not None and model.params["sh0"].grad is not None


@pytest.mark.parametrize("kwargs, message", [
    ({"num_points": 0}, "num_points"),
    ({"init_scale": 0.0}, "init_scale"),
    ({"init_scale": -1.0}, "init_scale"),
    ({"init_opacity": 1.0}, "init_opacity"),
    ({"init_opacity": 0.0}, "init_opacity"),
    ({"sh_degree": 4}, "sh_degree"),
])
def test_impossible_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        GaussianModel.random_init(1.0, blender=False, **kwargs)


def test_impossible_inputs_raise():
    with pytest.raises(ValueError, match="scene_radius"):
        GaussianModel.random_init(0.0, blender=False)
    with pytest.raises(ValueError, match="points"):
        GaussianModel.from_points(torch.zeros(0, 3), torch.zeros(0, 3))
    with pytest.raises(ValueError, match="colors"):
        GaussianModel.from_points(torch.zeros(4, 3), torch.zeros(4, 4))
    with pytest.raises(ValueError, match="NaN"):
        GaussianModel.from_points(torch.full((4, 3), float("nan")), torch.zeros(4, 3))
