"""The 3DGS adaptive density control baseline: statistics, clone / split / prune, opacity reset, budget."""

from __future__ import annotations

import math

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import OptimConfig, make_optimizers
from mcsplat.render import RenderResult, render
from mcsplat.strategy import ADCConfig, ADCStrategy, Strategy

RADIUS = 1.0
W = H = 100  # NDC factor 50 on both axes

# The hand-made configuration: (largest scale, opacity, pixel gradient x per view, visible)
#   percent_dense R = 0.01 separates small (clone) from large (split); threshold 2e-4 NDC = 4e-6 px at 50 px/NDC.
LAYOUT = [
    (0.005, 0.5, 1.2e-5, True),   # 0 small, mean NDC grad 3e-4 over two views -> clone
    (0.005, 0.6, 1.6e-5, True),   # 1 small, 4e-4                              -> clone
    (0.050, 0.7, 2.0e-5, True),   # 2 large, 5e-4                              -> split
    (0.050, 0.7, 4.0e-6, True),   # 3 large, 1e-4                              -> nothing
    (0.005, 0.7, 4.0e-6, True),   # 4 small, 1e-4                              -> nothing
    (0.005, 0.003, 0.0, True),    # 5 opacity below 0.005                      -> pruned
    (0.500, 0.7, 0.0, True),      # 6 larger than 0.1 R in world space         -> pruned after step 3000
    (0.005, 0.7, 1.0, False),     # 7 invisible: its (huge) gradient must not count -> nothing
]


def hand_made_model() -> GaussianModel:
    g = torch.Generator().manual_seed(0)
    n = len(LAYOUT)
    model = GaussianModel.empty(n)
    with torch.no_grad():
        model.params["means"].copy_(torch.randn(n, 3, generator=g))
        model.params["quats"].copy_(torch.randn(n, 4, generator=g))
        model.params["sh0"].copy_(torch.randn(n, 1, 3, generator=g))
        model.params["shN"].copy_(torch.randn(n, 15, 3, generator=g))
        for i, (scale, opacity, _, _) in enumerate(LAYOUT):
            model.params["log_scales"][i] = torch.log(torch.tensor([scale, scale * 0.5, scale * 0.3]))
            model.params["opacity_logits"][i] = math.log(opacity / (1 - opacity))
    return model


def fake_result(pixel_grads: torch.Tensor, radii: torch.Tensor) -> RenderResult:
    n = pixel_grads.shape[0]
    means2d = torch.zeros(n, 2, requires_grad=True)
    means2d.grad = pixel_grads.clone()
    return RenderResult(rgb=torch.zeros(1, 1, 3), alpha=torch.zeros(1, 1), depth_sum=torch.zeros(1, 1),
                        means2d=means2d, radii=radii.to(torch.int32), depths=torch.ones(n),
                        contributed=radii > 0)


def feed_two_views(strategy: ADCStrategy, model: GaussianModel, step: int = 10) -> None:
    """View 1: the LAYOUT gradients; view 2: zero gradients. Radius 5 px where visible."""
    grads = torch.tensor([[g, 0.0] for _, _, g, _ in LAYOUT])
    radii = torch.tensor([5 if visible else 0 for *_, visible in LAYOUT])
    strategy.step_post_backward(step, model, fake_result(grads, radii), W, H)
    strategy.step_post_backward(step, model, fake_result(torch.zeros_like(grads), radii), W, H)


def prepared(config: ADCConfig | None = None):
    model = hand_made_model()
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    # two Adam steps so that the moments are non-zero
    g = torch.Generator().manual_seed(1)
    for _ in range(2):
        loss = sum((model.params[k] * torch.randn(model.params[k].shape, generator=g)).sum() for k in PARAM_KEYS)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
    fresh = hand_made_model()
    with torch.no_grad():
        for k in PARAM_KEYS:
            model.params[k].copy_(fresh.params[k])
    strategy = ADCStrategy(config or ADCConfig(), RADIUS, torch.Generator().manual_seed(2))
    return model, optimizers, strategy


def test_statistics_use_ndc_units_visible_gaussians_and_max_radii():
    model, _, strategy = prepared()
    feed_two_views(strategy, model)
    mean_grad = strategy.gradients.total / strategy.gradients.views.clamp(min=1)
    expected = torch.tensor([g * W / 2 / 2 for _, _, g, _ in LAYOUT])
    expected[7] = 0.0
    torch.testing.assert_close(mean_grad, expected)
    assert strategy.gradients.views.tolist() == [2] * 7 + [0]
    assert strategy.max_radii.tolist() == [5.0] * 7 + [0.0]
    # width and height scale x and y separately
    wide = ADCStrategy(ADCConfig(), RADIUS, torch.Generator())
    two = GaussianModel.empty(2)
    wide.step_post_backward(0, two, fake_result(torch.tensor([[5e-6, 0.0], [0.0, 5e-6]]), torch.tensor([3, 7])),
                            20, 100)
    torch.testing.assert_close(wide.gradients.total, torch.tensor([5e-6 * 10, 5e-6 * 50]))
    assert wide.max_radii.tolist() == [3.0, 7.0]


def test_clone_split_prune_counts_on_the_hand_made_configuration():
    model, optimizers, strategy = prepared()
    before = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    feed_two_views(strategy, model)
    info = strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4)
    assert (info.cloned, info.split, info.pruned) == (2, 1, 1)
    # 8 + 2 clones + 2 children - 1 split parent - 1 pruned
    assert info.num_gaussians == model.num_gaussians == 10
    # survivors in order: 0 1 3 4 6 7, then the clones of 0 and 1, then the two children of 2
    survivors = [0, 1, 3, 4, 6, 7]
    for key in PARAM_KEYS:
        param = model.params[key].detach()
        assert torch.equal(param[:6], before[key][survivors])
        assert torch.equal(param[6:8], before[key][[0, 1]])
        if key not in ("means", "log_scales"):
            assert torch.equal(param[8:10], before[key][[2, 2]])
        state = optimizers[key].state[model.params[key]]
        exp_avg, exp_avg_sq = state["exp_avg"], state["exp_avg_sq"]
        assert exp_avg.shape[0] == 10
        assert torch.count_nonzero(exp_avg[6:]) == 0 and torch.count_nonzero(exp_avg_sq[6:]) == 0
        assert torch.count_nonzero(exp_avg_sq[:6]) > 0
    # split children: scales / 1.6, positions drawn from the parent's Gaussian (within 5 sigma)
    torch.testing.assert_close(model.scales[8:].detach(), torch.exp(before["log_scales"][[2, 2]]) / 1.6)
    offset = model.means[8:].detach() - before["means"][2]
    assert offset.norm(dim=1).max() < 5 * 0.05 and offset.norm(dim=1).min() > 0
    assert not torch.equal(model.means[8], model.means[9])
    # accumulators are reset for the new set
    assert strategy.gradients.total.shape[0] == 10 and strategy.gradients.total.abs().sum() == 0
    assert strategy.gradients.views.sum() == 0 and strategy.max_radii.sum() == 0


def test_world_size_prune_starts_after_the_first_reset():
    model, optimizers, strategy = prepared()
    feed_two_views(strategy, model)
    info = strategy.step_post_optimizer(3100, model, optimizers, means_lr=1e-4)
    assert (info.cloned, info.split, info.pruned) == (2, 1, 2)
    assert model.num_gaussians == 9
    assert model.scales.detach().max() < 0.1 * RADIUS


def test_screen_size_prune_is_off_by_default_and_available():
    for flag, expected_pruned in ((False, 0), (True, 1)):
        model = hand_made_model()
        with torch.no_grad():
            model.params["log_scales"][6] = math.log(0.005)  # no world-size prune
            model.params["opacity_logits"][5] = 0.0          # no opacity prune
        optimizers = make_optimizers(model, OptimConfig(), RADIUS)
        strategy = ADCStrategy(ADCConfig(screen_size_prune=flag), RADIUS, torch.Generator())
        radii = torch.tensor([5, 5, 5, 5, 5, 5, 25, 0])
        strategy.step_post_backward(10, model, fake_result(torch.zeros(8, 2), radii), W, H)
        info = strategy.step_post_optimizer(3100, model, optimizers, means_lr=1e-4)
        assert info.pruned == expected_pruned


def test_opacity_reset():
    model, optimizers, strategy = prepared()
    with torch.no_grad():
        model.params["opacity_logits"][5] = math.log(0.008 / 0.992)  # below the reset value: stays
    before_o = model.opacities.detach().clone()
    means_state = optimizers["means"].state[model.params["means"]]["exp_avg"].clone()
    info = strategy.step_post_optimizer(3000, model, optimizers, means_lr=1e-4)
    assert info.reset is True and model.num_gaussians == 8
    o = model.opacities.detach()
    torch.testing.assert_close(o, torch.clamp(before_o, max=0.01))
    state = optimizers["opacity_logits"].state[model.params["opacity_logits"]]
    assert torch.count_nonzero(state["exp_avg"]) == 0 and torch.count_nonzero(state["exp_avg_sq"]) == 0
    assert torch.equal(optimizers["means"].state[model.params["means"]]["exp_avg"], means_state)


def test_schedule_is_0_based_like_gsplat():
    strategy = ADCStrategy(ADCConfig(), RADIUS, torch.Generator())
    densify = [s for s in range(30_001) if strategy.is_densify_step(s)]
    assert densify[0] == 600 and densify[-1] == 14_900 and len(densify) == 144
    assert [s for s in range(30_001) if strategy.is_reset_step(s)] == [3000, 6000, 9000, 12_000]
    white = ADCStrategy(ADCConfig(reset_at_start=True), RADIUS, torch.Generator())
    assert white.is_reset_step(500)
    # no statistics after densify_stop
    model = hand_made_model()
    strategy.step_post_backward(15_000, model, fake_result(torch.ones(8, 2), torch.ones(8)), W, H)
    assert strategy.gradients.total is None


def test_budget_keeps_the_largest_gradients_and_is_never_exceeded():
    model, optimizers, strategy = prepared(ADCConfig(cap_max=10))
    feed_two_views(strategy, model)
    info = strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4)
    # budget 2: the split of 2 (5e-4) and the clone of 1 (4e-4), not the clone of 0 (3e-4)
    assert (info.cloned, info.split) == (1, 1)
    assert model.num_gaussians == 8 + 1 + 2 - 1 - 1
    # at the cap, nothing is added any more; repeated rounds never exceed it
    for step in range(700, 2000, 100):
        grads = torch.full((model.num_gaussians, 2), 1e-4)
        strategy.step_post_backward(step, model, fake_result(grads, torch.full((model.num_gaussians,), 3)), W, H)
        strategy.step_post_optimizer(step, model, optimizers, means_lr=1e-4)
        assert model.num_gaussians <= 10
    assert model.num_gaussians == 10


def test_state_round_trip_gives_the_same_densification():
    model_a, opt_a, strategy_a = prepared()
    model_b, opt_b, _ = prepared()
    feed_two_views(strategy_a, model_a)
    strategy_b = ADCStrategy(ADCConfig(), RADIUS, torch.Generator().manual_seed(2))
    strategy_b.load_state_dict(strategy_a.state_dict())
    assert torch.equal(strategy_b.gradients.total, strategy_a.gradients.total)
    strategy_a.step_post_optimizer(600, model_a, opt_a, means_lr=1e-4)
    strategy_b.step_post_optimizer(600, model_b, opt_b, means_lr=1e-4)
    for key in PARAM_KEYS:
        assert torch.equal(model_a.params[key], model_b.params[key])
    with pytest.raises(ValueError, match="not an ADC"):
        strategy_b.load_state_dict({"strategy": "mcmc"})
    assert isinstance(strategy_a, Strategy)
    assert float(strategy_a.regularization(model_a)) == 0.0


def test_with_the_real_renderer():
    """Statistics from an actual render: visible Gaussians get counts, those behind the camera none."""
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    camera = Camera(K=intrinsics(30.0, 30.0, 16.0, 16.0), world_to_camera=w2c, width=32, height=32)
    g = torch.Generator().manual_seed(3)
    points = torch.randn(40, 3, generator=g) * 0.4
    points[-5:, 2] = -10.0  # behind the camera
    model = GaussianModel.from_points(points, torch.rand(40, 3, generator=g), init_opacity=0.5, sh_degree=0)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = ADCStrategy(ADCConfig(densify_start=0, densify_every=2, grad_threshold=1e-5), RADIUS,
                           torch.Generator().manual_seed(4))
    target = torch.rand(32, 32, 3, generator=g)
    for step in range(1, 3):
        result = render(model, camera)
        (result.rgb - target).abs().mean().backward()
        strategy.step_post_backward(step, model, result, camera.width, camera.height)
        if step == 1:
            visible = result.visible
            assert visible[:-5].any() and not visible[-5:].any()
            assert (strategy.gradients.views[visible] == 1).all() and (strategy.gradients.views[~visible] == 0).all()
            assert (strategy.gradients.total[visible] > 0).any() and (strategy.gradients.total[~visible] == 0).all()
            torch.testing.assert_close(strategy.max_radii[visible], result.radii[visible].float())
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        info = strategy.step_post_optimizer(step, model, optimizers, means_lr=1e-4)
    assert info.cloned + info.split > 0
    assert info.num_gaussians == model.num_gaussians == 40 + info.cloned + info.split - info.pruned
    for key in PARAM_KEYS:
        assert optimizers[key].param_groups[0]["params"][0] is model.params[key]
    result = render(model, camera)
    result.rgb.sum().backward()


def test_missing_gradient_is_an_error():
    model = hand_made_model()
    strategy = ADCStrategy(ADCConfig(), RADIUS, torch.Generator())
    result = fake_result(torch.zeros(8, 2), torch.ones(8))
    result.means2d.grad = None
    with pytest.raises(RuntimeError, match="means2d.grad"):
        strategy.step_post_backward(0, model, result, W, H)


@pytest.mark.parametrize("kwargs, message", [
    ({"cap_max": 0}, "cap_max"), ({"grad_threshold": -1.0}, "grad_threshold"),
    ({"densify_every": 0}, "densify_every"), ({"reset_every": 0}, "reset_every"),
    ({"min_opacity": 1.5}, "min_opacity"), ({"percent_dense": -0.1}, "percent_dense"),
    ({"max_world_size": float("inf")}, "max_world_size"),
])
def test_impossible_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ADCConfig(**kwargs)
    with pytest.raises(ValueError, match="scene_radius"):
        ADCStrategy(ADCConfig(), -1.0, torch.Generator())


def test_the_baseline_is_3dgs_as_the_paper_ran_it(tmp_path):
    # 3DGS resets opacities at its first densification step on white backgrounds, and starts from 1.0 x kNN scales
    # at opacity 0.1; MCMC keeps its own (0.1 x kNN, 0.5). Explicit options still win.
    assert ADCStrategy(ADCConfig(), RADIUS, torch.Generator(), white_background=True).is_reset_step(500)
    assert not ADCStrategy(ADCConfig(), RADIUS, torch.Generator(), white_background=False).is_reset_step(500)
    assert not ADCStrategy(ADCConfig(reset_at_start=False), RADIUS, torch.Generator(),
                           white_background=True).is_reset_step(500)
    from mcsplat.config import ModelConfig, TrainConfig

    adc, mcmc = TrainConfig(data=tmp_path, strategy="adc"), TrainConfig(data=tmp_path)
    assert (adc.model.init_scale, adc.model.init_opacity) == (1.0, 0.1)
    assert (mcmc.model.init_scale, mcmc.model.init_opacity) == (0.1, 0.5)
    chosen = TrainConfig(data=tmp_path, strategy="adc", model=ModelConfig(init_scale=0.1, init_opacity=0.5))
    assert (chosen.model.init_scale, chosen.model.init_opacity) == (0.1, 0.5)


def test_a_white_background_run_resets_at_the_first_densification(tmp_path):
    from mcsplat.config import TrainConfig
    from mcsplat.run.events import RefineDone
    from mcsplat.train import train

    from tests.support.helpers import REPO

    resets = []
    config = TrainConfig(data=REPO / "data" / "lego_demo", out=tmp_path / "run", strategy="adc", steps=60, quiet=True,
                         lpips_net="alex", save_every=0, save_renders=False, scale_schedule=False,
                         adc=ADCConfig(densify_start=20, densify_every=20, reset_every=1000))
    train(config, [lambda event: resets.append(event.step) if isinstance(event, RefineDone)
                   and event.report.reset else None])
    assert resets == [20]
