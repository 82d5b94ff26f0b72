"""The MCMC strategy: Eq. 9, SGLD noise, relocation, growth, the failure cases (all dead, 2^24 and more), the schedule."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.integrate import quad

from mcsplat.camera import Camera, intrinsics
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import OptimConfig, make_optimizers
from mcsplat.render import Splats, render
from mcsplat.geometry.sh import SH_C0
from mcsplat.strategy import MCMCConfig, MCMCStrategy, Strategy
from mcsplat.strategy import mcmc as mcmc_module
from mcsplat.strategy.mcmc import grow, inject_noise, noise_gate, prune_to_cap, relocate_dead
from mcsplat.strategy.relocation import MAX_OPACITY, binomial_table, relocation_params, sample_by_weight
from tests.support.helpers import random_adam_step

RADIUS = 2.0


# ------------------------------------------------------------------------------------------------------ helpers
def make_model(opacities, seed: int = 0, dtype=torch.float32) -> GaussianModel:
    """Random Gaussians with the given opacities."""
    opacities = torch.as_tensor(opacities, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.empty(opacities.shape[0], dtype=dtype)
    with torch.no_grad():
        for key in PARAM_KEYS:
            model.params[key].copy_(torch.randn(model.params[key].shape, generator=g, dtype=dtype))
        model.params["log_scales"].mul_(0.3).sub_(2.0)
        model.params["opacity_logits"].copy_(torch.logit(opacities).to(dtype))
    return model


def adam_with_moments(model: GaussianModel, seed: int = 0):
    """Optimizers that have taken two steps (non-zero moments), with the parameters restored afterwards."""
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    saved = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    g = torch.Generator().manual_seed(seed)
    for _ in range(2):
        random_adam_step(model, optimizers, g)
    with torch.no_grad():
        for k in PARAM_KEYS:
            model.params[k].copy_(saved[k])
    return optimizers


def moments(optimizers, key):
    opt = optimizers[key]
    state = opt.state[opt.param_groups[0]["params"][0]]
    return state["exp_avg"], state["exp_avg_sq"], state["step"]


def snapshot(model, optimizers):
    params = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    state = {k: tuple(t.clone() for t in moments(optimizers, k)) for k in PARAM_KEYS}
    return params, state


# ------------------------------------------------------------------------------------------------------ Eq. 9
OPACITIES = [0.006, 0.05, 0.3, 0.7, 0.95, 0.999]


def test_binomial_table():
    table = binomial_table(51)
    assert table.shape == (51, 51)
    assert table[0, 0] == 1 and table[50, 25] == math.comb(50, 25) and table[10, 3] == 120 and table[3, 5] == 0


@pytest.mark.parametrize("n_copies", [1, 2, 3, 7, 20, 51])
def test_eq9_opacity_keeps_the_centre_value(n_copies):
    o = torch.tensor(OPACITIES, dtype=torch.float64)
    new_o, _ = relocation_params(o, torch.ones(len(o), 3, dtype=torch.float64),
                                 torch.full((len(o),), n_copies), min_opacity=0.0)
    torch.testing.assert_close((1 - new_o) ** n_copies, 1 - o, rtol=1e-12, atol=0)


@pytest.mark.parametrize("n_copies", [1, 2, 3, 7, 20, 51])
def test_eq9_scale_matches_a_numerical_integral_of_the_composited_profile(n_copies):
    """The 1D slice through the centre, composited over N copies, integrates to the original's integral."""
    o = torch.tensor(OPACITIES, dtype=torch.float64)
    scales = torch.tensor([[1.0, 0.5, 2.0]], dtype=torch.float64).expand(len(o), 3)
    new_o, new_s = relocation_params(o, scales, torch.full((len(o),), n_copies), min_opacity=0.0)
    for i in range(len(o)):
        for axis in range(3):
            s_old, s_new, o_new = float(scales[i, axis]), float(new_s[i, axis]), float(new_o[i])

            def composite(x):
                return 1.0 - (1.0 - o_new * math.exp(-0.5 * (x / s_new) ** 2)) ** n_copies

            def original(x):
                return float(o[i]) * math.exp(-0.5 * (x / s_old) ** 2)

            reach = 12 * max(s_old, s_new)
            got = quad(composite, -reach, reach, epsabs=0, epsrel=1e-12, limit=200)[0]
            want = quad(original, -reach, reach, epsabs=0, epsrel=1e-12, limit=200)[0]
            assert got == pytest.approx(want, rel=1e-9), (float(o[i]), n_copies, axis)
            # and the copies are narrower than the original (the paper's point against plain cloning)
            if n_copies > 1:
                assert s_new < s_old


def test_eq9_clamps_n_and_the_opacity_after_the_scale():
    o = torch.tensor([0.4, 0.4], dtype=torch.float64)
    s = torch.ones(2, 3, dtype=torch.float64)
    at_cap = relocation_params(o, s, torch.tensor([51, 51]))
    above = relocation_params(o, s, torch.tensor([80, 1000]))
    assert torch.equal(at_cap[0], above[0]) and torch.equal(at_cap[1], above[1])
    assert torch.equal(relocation_params(o, s, torch.tensor([60, 60]), n_max=50)[0],
                       relocation_params(o, s, torch.tensor([50, 50]), n_max=50)[0])
    # o = 0.006 shared by 5: o_new ~ 0.0012 < 0.005 is clamped up, the scale is that of the unclamped o_new.
    low = torch.tensor([0.006], dtype=torch.float64)
    clamped_o, clamped_s = relocation_params(low, s[:1], torch.tensor([5]), min_opacity=0.005)
    free_o, free_s = relocation_params(low, s[:1], torch.tensor([5]), min_opacity=0.0)
    assert float(free_o) < 0.005 and float(clamped_o) == 0.005
    assert torch.equal(clamped_s, free_s)
    # the top clamp (1 - 1.19e-7), and a source at exactly 1 gives finite results
    top_o, top_s = relocation_params(torch.tensor([1.0]), torch.ones(1, 3), torch.tensor([1]))
    assert float(top_o) <= MAX_OPACITY and torch.isfinite(top_s).all()


def render_camera(size: int = 64) -> Camera:
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    # principal point on the centre of pixel (size/2, size/2): the Gaussian at the origin lands there
    return Camera(K=intrinsics(60.0, 60.0, size / 2 + 0.5, size / 2 + 0.5), world_to_camera=w2c,
                  width=size, height=size)


def model_splats(model: GaussianModel, rows=slice(None)) -> Splats:
    return Splats(means=model.means.detach()[rows], quats=model.quats.detach()[rows],
                  scales=model.scales.detach()[rows], opacities=model.opacities.detach()[rows],
                  sh=model.sh.detach()[rows])


# Measured on 64x64, black background, white Gaussian with scales (0.25, 0.15, 0.2) rotated, 3 units away:
# centre pixel |difference| <= 6e-8 (float32 rounding); over the image max |difference| = 0.067 and mean
# |difference| = 0.0038 at worst (o = 0.9, N = 5), against 0.53 max for plain cloning. Eq. 9 matches the centre
# value and the 1D integral through the centre, not every pixel of the 2D footprint, hence the off-centre residue.
@pytest.mark.parametrize("opacity", [0.3, 0.6, 0.9])
@pytest.mark.parametrize("n_copies", [2, 3, 5])
def test_relocating_into_n_copies_keeps_the_rendered_image(opacity, n_copies):
    camera = render_camera()
    opacities = [opacity] + [0.001] * (n_copies - 1)  # one live Gaussian, the others dead
    model = make_model(opacities, seed=1)
    with torch.no_grad():
        model.params["means"][0] = 0.0
        model.params["quats"][0] = torch.tensor([0.9, 0.2, 0.1, 0.3])
        model.params["log_scales"][0] = torch.log(torch.tensor([0.25, 0.15, 0.2]))
        model.params["sh0"][0] = 0.5 / SH_C0   # white
        model.params["shN"][0] = 0.0
    original = model_splats(model, slice(0, 1))
    before = render(original, camera).rgb[..., 0]
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    slots, sources = relocate_dead(model, optimizers, torch.Generator().manual_seed(0))
    assert sorted(slots.tolist()) == list(range(1, n_copies)) and set(sources.tolist()) == {0}
    assert torch.allclose((1 - model.opacities.detach()) ** n_copies, torch.tensor(1 - opacity), rtol=0, atol=1e-6)
    after = render(model_splats(model), camera).rgb[..., 0]
    centre = before.shape[0] // 2
    assert before[centre, centre] == pytest.approx(opacity, abs=1e-6)
    assert abs(float(after[centre, centre] - before[centre, centre])) <= 1e-6
    difference = (after - before).abs()
    assert float(difference.max()) <= 0.075
    assert float(difference.mean()) <= 0.005
    # plain cloning (same opacity and scale) is far off, as the paper's Fig. 1 says
    cloned = render(Splats(**{f: getattr(original, f).repeat_interleave(n_copies, 0)
                              for f in ("means", "quats", "scales", "opacities", "sh")}), camera).rgb[..., 0]
    assert float((cloned - before).abs().max()) > 2.5 * float(difference.max())


# ------------------------------------------------------------------------------------------------------- noise
def test_noise_gate_values_of_spec_section_4():
    o = torch.tensor([0.005, 0.01, 0.02, 0.05, 0.1, 0.5], dtype=torch.float64)
    expected = [0.5, 0.3775, 0.1824, 0.01099, 7.48e-5, 3.1e-22]
    for got, want in zip(noise_gate(o).tolist(), expected):
        assert got == pytest.approx(want, rel=2e-3)


def test_noise_is_gated_covariance_shaped_and_only_on_positions():
    model = make_model([0.001] * 3 + [0.5] * 3, seed=2, dtype=torch.float64)
    optimizers = adam_with_moments(model)
    params, state = snapshot(model, optimizers)
    factor = 5e5 * 1.6e-4 * RADIUS
    inject_noise(model, factor, torch.Generator().manual_seed(11))
    # exactly factor * gate(o) * Sigma @ eta with eta the generator's standard normals
    eta = torch.randn(6, 3, generator=torch.Generator().manual_seed(11), dtype=torch.float64)
    sigma = model.covariances().detach()
    gate = torch.sigmoid(-100 * (model.opacities.detach() - 0.005))
    expected = factor * gate[:, None] * (sigma @ eta[:, :, None])[:, :, 0]
    displacement = model.means.detach() - params["means"]
    torch.testing.assert_close(displacement[:3], expected[:3], rtol=1e-10, atol=0)
    assert displacement[:3].abs().min() > 1e-3                    # dead ones move (gate ~ 0.6)
    assert expected[3:].abs().max() < 1e-18 * factor              # opaque ones (o = 0.5): gate ~ 3e-22
    assert displacement[3:].abs().max() < 1e-15                   # (below the float64 resolution of the means)
    for key in PARAM_KEYS:                                        # nothing else changes, Adam state included
        if key != "means":
            assert torch.equal(model.params[key].detach(), params[key])
        for a, b in zip(moments(optimizers, key), state[key]):
            assert torch.equal(a, b)


def test_noise_statistics_zero_mean_and_covariance_proportional_to_sigma_squared():
    """Sample mean 0 and covariance (factor gate)^2 Sigma^2, measured over 40k independent Gaussians."""
    m = 40_000
    model = make_model([0.002] * m, seed=3, dtype=torch.float64)
    with torch.no_grad():
        model.params["means"].zero_()
        model.params["quats"].copy_(torch.tensor([0.8, -0.3, 0.4, 0.2], dtype=torch.float64))
        model.params["log_scales"].copy_(torch.log(torch.tensor([0.5, 0.2, 0.1], dtype=torch.float64)))
    factor = 3.0
    inject_noise(model, factor, torch.Generator().manual_seed(4))
    x = model.means.detach()
    sigma = model.covariances().detach()[0]
    gate = 1.0 / (1.0 + math.exp(100 * (0.002 - 0.005)))
    expected_cov = (factor * gate) ** 2 * sigma @ sigma
    std = torch.sqrt(torch.diagonal(expected_cov))
    assert (x.mean(0).abs() <= 4.5 * std / math.sqrt(m)).all()
    sample_cov = torch.cov(x.T)
    assert (sample_cov - expected_cov).abs().max() <= 0.03 * expected_cov.abs().max()
    # not Sigma (the square root would be the "wrong" scaling): the ratio of the principal variances is s^4
    eig = torch.linalg.eigvalsh(sample_cov)
    assert eig[-1] / eig[0] == pytest.approx((0.5 / 0.1) ** 4, rel=0.1)


# -------------------------------------------------------------------------------------------------- relocation
def test_relocation_moves_dead_onto_live_and_zeroes_moments_at_sources_only():
    opacities = torch.cat([torch.linspace(0.05, 0.95, 40), torch.full((20,), 0.003)])
    model = make_model(opacities, seed=5)
    optimizers = adam_with_moments(model)
    params, state = snapshot(model, optimizers)
    old_o = model.opacities.detach().clone()
    slots, sources = relocate_dead(model, optimizers, torch.Generator().manual_seed(6))
    assert model.num_gaussians == 60
    assert sorted(slots.tolist()) == list(range(40, 60))
    assert (sources < 40).all()
    # dead slots receive their source's position, rotation and colour; source and copies end identical
    for key in ("means", "quats", "sh0", "shN"):
        assert torch.equal(model.params[key][slots].detach(), params[key][sources])
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key][slots].detach(), model.params[key][sources].detach())
    # Eq. 9 per source: shared by (times sampled + 1)
    counts = torch.bincount(sources, minlength=60)
    new_o = model.opacities.detach()
    for s in sources.unique().tolist():
        n = int(counts[s]) + 1
        assert float((1 - new_o[s]) ** n) == pytest.approx(float(1 - old_o[s]), abs=2e-6)
        assert (model.scales[s] < torch.exp(params["log_scales"][s])).all()
    untouched = torch.ones(60, dtype=torch.bool)
    untouched[sources] = False
    untouched[slots] = False
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key][untouched].detach(), params[key][untouched])
    # Adam: zero exactly at the sources, the dead slots keep their moments, the step counter is untouched
    source_mask = torch.zeros(60, dtype=torch.bool)
    source_mask[sources] = True
    for key in PARAM_KEYS:
        exp_avg, exp_avg_sq, step = moments(optimizers, key)
        assert torch.count_nonzero(exp_avg[source_mask]) == 0 and torch.count_nonzero(exp_avg_sq[source_mask]) == 0
        assert torch.equal(exp_avg[~source_mask], state[key][0][~source_mask])
        assert torch.equal(exp_avg_sq[~source_mask], state[key][1][~source_mask])
        assert torch.equal(step, state[key][2])
    assert (model.opacities.detach() >= 0.005 - 1e-9).all()


def test_relocation_samples_sources_in_proportion_to_opacity():
    model = make_model([0.8, 0.2] + [0.001] * 4000, seed=7)
    _, sources = relocate_dead(model, make_optimizers(model, OptimConfig(), RADIUS),
                               torch.Generator().manual_seed(8))
    share = float((sources == 0).double().mean())
    assert share == pytest.approx(0.8, abs=0.03)  # 5 sigma


def test_all_dead_skips_relocation_with_a_warning():
    model = make_model([0.001] * 30, seed=9)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    before = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    with pytest.warns(RuntimeWarning, match="nothing to copy from"):
        slots, _ = relocate_dead(model, optimizers, torch.Generator().manual_seed(0))
    assert slots.numel() == 0
    strategy = MCMCStrategy(MCMCConfig(cap_max=100), RADIUS, torch.Generator().manual_seed(0))
    with pytest.warns(RuntimeWarning, match="nothing to copy from"):
        info = strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4)
    assert info.relocated == 0 and info.added == 0 and model.num_gaussians == 30
    for key in ("opacity_logits", "log_scales", "sh0", "quats"):
        assert torch.equal(model.params[key].detach(), before[key])


def test_a_relocation_at_the_cap_that_finds_most_dead_warns_once():
    # 6 of 10 dead at the cap: the collapse the bird showed at 1M (the share then feeds itself).
    model = make_model([0.5] * 4 + [0.001] * 6, seed=11)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=10), RADIUS, torch.Generator().manual_seed(0))
    with pytest.warns(RuntimeWarning, match=r"60% of the 10 Gaussians were dead.*--cap-max"):
        info = strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4)
    assert info.relocated == 6
    model.params["opacity_logits"].data[4:] = -10.0  # dead again: no second warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        strategy.step_post_optimizer(700, model, optimizers, means_lr=1e-4)


@pytest.mark.parametrize("opacities, cap", [([0.5] * 6 + [0.001] * 4, 10),   # 40% dead: healthy enough
                                             ([0.5] * 4 + [0.001] * 6, 1000)])  # below the cap: still growing
def test_no_collapse_warning_below_half_dead_or_below_the_cap(opacities, cap):
    model = make_model(opacities, seed=12)
    strategy = MCMCStrategy(MCMCConfig(cap_max=cap), RADIUS, torch.Generator().manual_seed(0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        strategy.step_post_optimizer(600, model, make_optimizers(model, OptimConfig(), RADIUS), means_lr=1e-4)


def test_nothing_dead_changes_nothing():
    model = make_model([0.5] * 10, seed=10)
    optimizers = adam_with_moments(model)
    params, state = snapshot(model, optimizers)
    slots, sources = relocate_dead(model, optimizers, torch.Generator().manual_seed(0))
    assert slots.numel() == 0 and sources.numel() == 0
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key].detach(), params[key])
        assert torch.equal(moments(optimizers, key)[0], state[key][0])


# ------------------------------------------------------------------------------------------------------ growth
def test_growth_appends_five_percent_copies_with_zero_moments():
    model = make_model(torch.linspace(0.1, 0.9, 100), seed=11)
    optimizers = adam_with_moments(model)
    params, state = snapshot(model, optimizers)
    old_o = model.opacities.detach().clone()
    sources = grow(model, optimizers, torch.Generator().manual_seed(12), cap_max=1000)
    assert model.num_gaussians == 105 and sources.numel() == 5
    for key in PARAM_KEYS:
        param = model.params[key].detach()
        assert torch.equal(param[100:], param[sources])  # appended copies equal their (updated) sources
        assert optimizers[key].param_groups[0]["params"][0] is model.params[key]
        exp_avg, exp_avg_sq, step = moments(optimizers, key)
        assert exp_avg.shape[0] == 105
        zero = torch.zeros(105, dtype=torch.bool)
        zero[100:] = True
        zero[sources] = True
        assert torch.count_nonzero(exp_avg[zero]) == 0 and torch.count_nonzero(exp_avg_sq[zero]) == 0
        assert torch.equal(exp_avg[~zero], state[key][0][~zero[:100]])
        assert torch.equal(step, state[key][2])
    for key in ("means", "quats", "sh0", "shN"):
        assert torch.equal(model.params[key][100:].detach(), params[key][sources])
    counts = torch.bincount(sources, minlength=100)
    for s in sources.unique().tolist():
        n = int(counts[s]) + 1
        assert float((1 - model.opacities.detach()[s]) ** n) == pytest.approx(float(1 - old_o[s]), abs=2e-6)


def test_growth_reaches_and_never_exceeds_cap_max():
    model = make_model(torch.linspace(0.1, 0.9, 100), seed=13)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=130), RADIUS, torch.Generator().manual_seed(14))
    counts = []
    for step in range(600, 1800, 100):
        info = strategy.step_post_optimizer(step, model, optimizers, means_lr=1e-5)
        counts.append(info.num_gaussians)
        assert model.num_gaussians <= 130
    assert counts[:6] == [105, 110, 115, 120, 126, 130] and set(counts[6:]) == {130}
    for key in PARAM_KEYS:
        assert moments(optimizers, key)[0].shape[0] == 130 if optimizers[key].state else True


def test_a_model_larger_than_cap_max_is_cut_to_its_most_opaque():
    opacities = torch.rand(300, generator=torch.Generator().manual_seed(15)) * 0.9 + 0.05
    model = make_model(opacities, seed=16)
    optimizers = adam_with_moments(model)
    params, state = snapshot(model, optimizers)
    strategy = MCMCStrategy(MCMCConfig(cap_max=200), RADIUS, torch.Generator().manual_seed(17))
    info = strategy.step_post_optimizer(650, model, optimizers, means_lr=0.0)  # not a refine step: untouched
    assert info.num_gaussians == 300
    info = strategy.step_post_optimizer(700, model, optimizers, means_lr=0.0)
    assert info.pruned == 100 and info.added == 0 and info.num_gaussians == 200
    kept = torch.sort(torch.topk(model_opacities(params), 200).indices).values
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key].detach(), params[key][kept])
        assert torch.equal(moments(optimizers, key)[0], state[key][0][kept])


def model_opacities(params):
    return torch.sigmoid(params["opacity_logits"])


def test_sfm_init_larger_than_cap_max():
    g = torch.Generator().manual_seed(18)
    model = GaussianModel.from_points(torch.randn(500, 3, generator=g), torch.rand(500, 3, generator=g))
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=120), RADIUS, torch.Generator().manual_seed(19))
    for step in range(0, 601):
        info = strategy.step_post_optimizer(step, model, optimizers, means_lr=1e-6)
    assert info.pruned == 380 and model.num_gaussians == 120
    assert prune_to_cap(model, optimizers, 120) == 0


def test_sampling_beyond_two_to_the_24():
    """torch.multinomial refuses more than 2^24 categories (gsplat #338); the sampler here does not."""
    n = (1 << 24) + 1000
    weights = torch.zeros(n)
    weights[[5, n - 600, n - 1]] = torch.tensor([1.0, 2.0, 1.0])
    samples = sample_by_weight(weights, 40_000, torch.Generator().manual_seed(20))
    assert set(samples.unique().tolist()) == {5, n - 600, n - 1}
    assert float((samples == n - 600).double().mean()) == pytest.approx(0.5, abs=0.015)
    with pytest.raises(ValueError, match="sum to zero"):
        sample_by_weight(torch.zeros(4), 3, torch.Generator())


def test_sampler_never_draws_zero_weights_and_is_reproducible():
    weights = torch.tensor([0.0, 0.3, 0.0, 0.0, 0.7, 0.0])
    a = sample_by_weight(weights, 5000, torch.Generator().manual_seed(21))
    b = sample_by_weight(weights, 5000, torch.Generator().manual_seed(21))
    assert torch.equal(a, b) and set(a.tolist()) == {1, 4}
    assert float((a == 4).double().mean()) == pytest.approx(0.7, abs=0.035)


# ---------------------------------------------------------------------------------------------- the strategy
def test_refine_schedule_is_gsplat_0_based():
    strategy = MCMCStrategy(MCMCConfig(), RADIUS, torch.Generator())
    refine = [s for s in range(0, 30_001) if strategy.is_refine_step(s)]
    assert refine[0] == 600 and refine[-1] == 24_900 and len(refine) == 244
    assert all(s % 100 == 0 for s in refine)


def test_step_order_refine_then_noise_and_noise_on_every_step(monkeypatch):
    calls = []
    for name in ("prune_to_cap", "relocate_dead", "grow", "inject_position_noise"):
        original = getattr(mcmc_module, name)

        def spy(*args, _name=name, _original=original, **kwargs):
            calls.append(_name)
            return _original(*args, **kwargs)
        monkeypatch.setattr(mcmc_module, name, spy)
    model = make_model(torch.linspace(0.001, 0.9, 50), seed=22)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=100), RADIUS, torch.Generator().manual_seed(23))
    strategy.step_post_optimizer(599, model, optimizers, means_lr=1e-4)
    assert calls == ["inject_position_noise"]
    calls.clear()
    strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4)
    assert calls == ["prune_to_cap", "relocate_dead", "grow", "inject_position_noise"]
    calls.clear()
    strategy.step_post_optimizer(25_000, model, optimizers, means_lr=1e-4)
    assert calls == ["inject_position_noise"]


def test_regularization_is_the_mean_of_activated_values():
    model = make_model(torch.linspace(0.1, 0.9, 20), seed=24)
    strategy = MCMCStrategy(MCMCConfig(), RADIUS, torch.Generator())
    reg = strategy.regularization(model)
    expected = 0.01 * torch.sigmoid(model.params["opacity_logits"]).mean() + \
        0.01 * torch.exp(model.params["log_scales"]).mean()
    torch.testing.assert_close(reg, expected)
    reg.backward()
    torch.testing.assert_close(model.params["opacity_logits"].grad,
                               0.01 * model.opacities.detach() * (1 - model.opacities.detach()) / 20)
    torch.testing.assert_close(model.params["log_scales"].grad, 0.01 * model.scales.detach() / 60)
    assert float(MCMCStrategy(MCMCConfig(opacity_reg=0, scale_reg=0)).regularization(model).detach()) == 0.0
    assert float(strategy.regularization(GaussianModel.empty(0))) == 0.0


def test_runs_are_reproducible_and_the_state_round_trips():
    def run(seed):
        model = make_model(torch.cat([torch.linspace(0.05, 0.9, 60), torch.full((10,), 0.001)]), seed=25)
        optimizers = make_optimizers(model, OptimConfig(), RADIUS)
        strategy = MCMCStrategy(MCMCConfig(cap_max=90), RADIUS, torch.Generator().manual_seed(seed))
        for step in range(590, 720):
            strategy.step_post_optimizer(step, model, optimizers, means_lr=1e-4)
        return model, strategy
    a, sa = run(26)
    b, _ = run(26)
    c, _ = run(27)
    for key in PARAM_KEYS:
        assert torch.equal(a.params[key], b.params[key])
    assert not torch.equal(a.means, c.means)
    fresh = MCMCStrategy(MCMCConfig(cap_max=90), RADIUS, torch.Generator())
    fresh.load_state_dict(sa.state_dict())
    assert isinstance(sa, Strategy)
    with pytest.raises(ValueError, match="not an MCMC"):
        fresh.load_state_dict({"strategy": "adc"})


def test_empty_model_does_not_crash():
    model = GaussianModel.empty(0)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(), RADIUS, torch.Generator())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert strategy.step_post_optimizer(600, model, optimizers, means_lr=1e-4).num_gaussians == 0


def test_short_training_run_with_the_real_renderer():
    """Render, loss, backward, Adam, strategy: counts grow to the cap, the optimizers follow every change."""
    camera = render_camera(32)
    g = torch.Generator().manual_seed(28)
    target_model = GaussianModel.from_points(torch.randn(60, 3, generator=g) * 0.5, torch.rand(60, 3, generator=g),
                                             init_opacity=0.8, sh_degree=0)
    with torch.no_grad():
        target = render(target_model, camera).rgb
    model = GaussianModel.random_init(0.4, blender=False, num_points=100, sh_degree=1, generator=g)
    with torch.no_grad():
        model.params["opacity_logits"][:10] = -7.0  # a few dead ones
    optimizers = make_optimizers(model, OptimConfig(), 0.4)
    config = MCMCConfig(cap_max=120, refine_start=2, refine_every=5, refine_stop=40)
    strategy = MCMCStrategy(config, 0.4, g)
    losses, relocated = [], 0
    for step in range(40):
        result = render(model, camera)
        loss = (result.rgb - target).abs().mean() + strategy.regularization(model)
        loss.backward()
        strategy.step_post_backward(step, model, result, camera.width, camera.height)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        info = strategy.step_post_optimizer(step, model, optimizers, means_lr=1.6e-4 * 0.4)
        relocated += info.relocated
        losses.append(float(loss.detach()))
        assert info.num_gaussians == model.num_gaussians <= 120
        for key in PARAM_KEYS:
            assert optimizers[key].param_groups[0]["params"][0] is model.params[key]
    assert model.num_gaussians == 120 and relocated >= 10
    assert np.mean(losses[-5:]) < np.mean(losses[:5])


@pytest.mark.parametrize("kwargs, message", [
    ({"cap_max": 0}, "cap_max"), ({"cap_max": -5}, "cap_max"), ({"noise_lr": -1.0}, "noise_lr"),
    ({"opacity_reg": -0.1}, "opacity_reg"), ({"scale_reg": float("nan")}, "scale_reg"),
    ({"refine_every": 0}, "refine_every"), ({"grow_rate": 0.9}, "grow_rate"), ({"min_opacity": 1.0}, "min_opacity"),
    ({"max_copies": 0}, "max_copies"), ({"refine_start": -1}, "refine_start"),
])
def test_impossible_options_raise(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MCMCConfig(**kwargs)


def test_impossible_radius_raises():
    with pytest.raises(ValueError, match="scene_radius"):
        MCMCStrategy(MCMCConfig(), 0.0, torch.Generator())
