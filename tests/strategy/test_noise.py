"""The noise and regulariser variants the paper ablates (strategy/noise.py, ADC's regularizers): each changes exactly
what it says, and the trainer hands the chosen schedule to the strategy."""

from __future__ import annotations

import math

import pytest
import torch

from mcsplat.cli import main
from mcsplat.config import TrainConfig
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import OptimConfig, means_lr_at
from mcsplat.planning import initial_plan, load_run_config
from mcsplat.strategy import MCMCConfig, MCMCStrategy
from mcsplat.strategy.adc import ADCConfig, ADCStrategy
from mcsplat.strategy.noise import inject_parameter_noise, inject_position_noise, noise_gate, noise_lr_at
from mcsplat.strategy.position_noise_simd import draw_key, fill_normals

from tests.strategy.test_mcmc import RADIUS, adam_with_moments, make_model, moments

OPACITIES = [0.001] * 3 + [0.5] * 3  # three nearly dead Gaussians (gate ~0.6), three opaque ones (gate ~3e-22)


def _normals(seed: int, *shapes: tuple[int, ...]) -> list[torch.Tensor]:
    """The standard normals the noise functions draw, in their order, from a generator seeded like theirs."""
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(shape, generator=g, dtype=torch.float64) for shape in shapes]


def test_without_the_covariance_the_noise_is_gate_times_eta():
    model = make_model(OPACITIES, seed=5, dtype=torch.float64)
    before = model.means.detach().clone()
    inject_position_noise(model, 2.0, torch.Generator().manual_seed(7), covariance=False)
    (eta,) = _normals(7, (6, 3))
    gate = noise_gate(model.opacities.detach())
    torch.testing.assert_close(model.means.detach() - before, 2.0 * gate[:, None] * eta, rtol=1e-10, atol=1e-15)
    assert (model.means.detach() - before)[3:].abs().max() < 1e-15  # the opaque ones stay


def test_without_the_gate_opaque_gaussians_move_by_sigma_eta():
    model = make_model(OPACITIES, seed=6, dtype=torch.float64)
    before = model.means.detach().clone()
    inject_position_noise(model, 2.0, torch.Generator().manual_seed(8), gated=False)
    (eta,) = _normals(8, (6, 3))
    expected = 2.0 * (model.covariances().detach() @ eta[:, :, None])[:, :, 0]
    torch.testing.assert_close(model.means.detach() - before, expected, rtol=1e-10, atol=1e-15)
    assert (model.means.detach() - before)[3:].abs().min() > 0


@pytest.mark.parametrize("covariance, gated", [(True, True), (False, True), (True, False)])
def test_the_cpu_kernel_adds_the_noise_of_the_torch_form(covariance, gated):
    """float32 on the CPU takes one kernel (strategy/position_noise_simd.py): the positions it moves agree with the
    formula in float64 from the same draw (the kernel's, from a key the generator gives), over two chunks of 16 and
    a short one, opacities from dead to opaque."""
    opacities = torch.linspace(0.0005, 0.9, 37)
    model = make_model(opacities, seed=3)
    with torch.no_grad():
        model.params["log_scales"].uniform_(-7.0, 1.0, generator=torch.Generator().manual_seed(4))
    before = model.means.detach().double().clone()
    inject_position_noise(model, 0.37, torch.Generator().manual_seed(9), covariance=covariance, gated=gated)
    eta = fill_normals(37, draw_key(torch.Generator().manual_seed(9))).double()  # the kernel's own draw
    covariances = GaussianModel.from_state_dict(model.state_dict()).double().covariances().detach()
    shaped = (covariances @ eta[:, :, None])[:, :, 0] if covariance else eta
    gate = noise_gate(torch.sigmoid(model.params["opacity_logits"].detach().double())) if gated else 1.0
    expected = before + 0.37 * (gate * torch.ones(37, dtype=torch.float64))[:, None] * shaped
    moved = model.means.detach().double()
    torch.testing.assert_close(moved, expected, rtol=1e-6, atol=1e-6)  # float32 positions of about 1
    assert (moved[-12:] != before[-12:]).all() if not gated else torch.equal(moved[-12:], before[-12:])
    assert (moved[:5] - before[:5]).abs().amax() > 1e-4  # the nearly dead ones do move


def test_the_cpu_kernels_draw_is_standard_normal_and_a_function_of_key_and_index():
    """The kernel's eta (normals_simd.h): mean 0, variance 1, no correlation between components or neighbours, the
    normal's quantiles; the same numbers for a Gaussian whatever the count, other numbers for another key."""
    eta = fill_normals(200_000, 12345).double()
    flat = eta.reshape(-1)
    assert flat.mean().abs() < 5 / 600_000 ** 0.5 and (flat.var() - 1).abs() < 0.01
    assert ((flat - flat.mean()) ** 4).mean() / flat.var() ** 2 == pytest.approx(3.0, abs=0.05)  # kurtosis
    correlations = torch.corrcoef(torch.cat([eta, eta.roll(1, 0)], dim=1).T)
    assert (correlations - torch.eye(6)).abs().max() < 0.01
    quantiles = torch.quantile(flat[:100_000], torch.tensor([0.01, 0.1, 0.5, 0.9, 0.99], dtype=torch.float64))
    torch.testing.assert_close(quantiles, torch.tensor([-2.3263, -1.2816, 0.0, 1.2816, 2.3263], dtype=torch.float64),
                               atol=0.02, rtol=0)
    assert torch.equal(fill_normals(37, 12345), eta[:37].float())
    assert not torch.isclose(fill_normals(37, 12346), eta[:37].float()).any()


def test_parameter_noise_moves_shape_and_opacity_of_the_gated_only():
    model = make_model(OPACITIES, seed=9, dtype=torch.float64)
    optimizers = adam_with_moments(model)
    moments_before = {key: [t.clone() for t in moments(optimizers, key)] for key in PARAM_KEYS}
    before = {key: model.params[key].detach().clone() for key in PARAM_KEYS}
    gate = noise_gate(model.opacities.detach())
    inject_parameter_noise(model, 0.5, torch.Generator().manual_seed(3))
    scales, quats, opacity = _normals(3, (6, 3), (6, 4), (6,))
    changed = {key: model.params[key].detach() - before[key] for key in PARAM_KEYS}
    torch.testing.assert_close(changed["log_scales"], 0.5 * gate[:, None] * scales, rtol=1e-10, atol=1e-15)
    torch.testing.assert_close(changed["quats"], 0.5 * gate[:, None] * quats, rtol=1e-10, atol=1e-15)
    torch.testing.assert_close(changed["opacity_logits"], 0.5 * 0.1 * gate * opacity, rtol=1e-10, atol=1e-15)
    assert changed["log_scales"][:3].abs().min() > 1e-3 and changed["log_scales"][3:].abs().max() < 1e-15
    for key in ("means", "sh0", "shN"):
        assert torch.equal(changed[key], torch.zeros_like(changed[key]))
    for key in PARAM_KEYS:  # bypassing the optimizer, like the position noise: its moments stay as they were
        assert all(torch.equal(a, b) for a, b in zip(moments(optimizers, key), moments_before[key]))


def test_ungated_parameter_noise_moves_the_opaque_too():
    model = make_model(OPACITIES, seed=9, dtype=torch.float64)
    before = model.params["quats"].detach().clone()
    inject_parameter_noise(model, 0.5, torch.Generator().manual_seed(3), gated=False)
    _, quats, _ = _normals(3, (6, 3), (6, 4), (6,))
    torch.testing.assert_close(model.params["quats"].detach() - before, 0.5 * quats, rtol=1e-10, atol=1e-15)


def test_the_strategy_adds_parameter_noise_only_when_asked_and_decays_it():
    def run(config: MCMCConfig, step: int) -> float:
        model = make_model(OPACITIES, seed=4)
        before = model.params["log_scales"].detach().clone()
        strategy = MCMCStrategy(config, RADIUS, torch.Generator().manual_seed(1))
        strategy.step_post_optimizer(step, model, adam_with_moments(model), means_lr=1e-4)
        return float((model.params["log_scales"].detach() - before)[:3].abs().mean())

    assert run(MCMCConfig(), 3) == 0
    early = run(MCMCConfig(noise_all_params=True, param_noise_decay=0.5), 1)
    late = run(MCMCConfig(noise_all_params=True, param_noise_decay=0.5), 3)
    assert early > 0 and late == pytest.approx(early / 4, rel=1e-5)  # 0.5^3 against 0.5^1


def test_noise_schedules_start_together_and_end_where_they_say():
    optim, steps = OptimConfig(), 3000
    start = means_lr_at(0, steps, optim, RADIUS)
    end = means_lr_at(steps, steps, optim, RADIUS)
    for schedule in ("lr", "linear", "neelakantan"):
        assert noise_lr_at(schedule, 0, steps, optim, RADIUS) == pytest.approx(start)
    assert noise_lr_at("lr", steps, steps, optim, RADIUS) == pytest.approx(start / 100)  # the paper's: 1.6e-4 -> 1.6e-6
    assert noise_lr_at("linear", steps, steps, optim, RADIUS) == pytest.approx(end)
    assert noise_lr_at("linear", steps // 2, steps, optim, RADIUS) == pytest.approx((start + end) / 2)
    # Neelakantan: variance ~ (1 + t)^-0.55 with t in steps of a 30,000-step run
    assert noise_lr_at("neelakantan", steps, steps, optim, RADIUS) == pytest.approx(start * 30_001 ** -0.275)
    assert noise_lr_at("neelakantan", steps // 10, steps, optim, RADIUS) == pytest.approx(start * 3001 ** -0.275)
    with pytest.raises(ValueError, match="unknown noise schedule"):
        noise_lr_at("cosine", 1, steps, optim, RADIUS)


def test_the_parameter_noise_decay_is_fitted_to_the_run_length(tmp_path):
    plan = initial_plan(TrainConfig(data=tmp_path, steps=3000))
    assert plan.schedule.param_noise_decay ** 3000 == pytest.approx(0.9995 ** 30_000, rel=1e-9)
    with pytest.raises(ValueError, match="param_noise_decay"):
        MCMCConfig(param_noise_decay=0.0)
    with pytest.raises(ValueError, match="noise_schedule"):
        MCMCConfig(noise_schedule="cosine")


def test_adc_takes_the_mcmc_regularizers_when_asked():
    model = make_model(torch.linspace(0.1, 0.9, 20).tolist(), seed=2)
    assert ADCStrategy(ADCConfig(), RADIUS).regularization(model) == 0
    reg = ADCStrategy(ADCConfig(opacity_reg=0.01, scale_reg=0.02), RADIUS).regularization(model)
    expected = 0.01 * model.opacities.mean() + 0.02 * model.scales.mean()
    assert float(reg.detach()) == pytest.approx(float(expected.detach()), rel=1e-6)
    with pytest.raises(ValueError, match="opacity_reg"):
        ADCConfig(opacity_reg=-1.0)


def test_the_trainer_hands_the_chosen_schedule_to_the_strategy(tmp_path, mini_demo, monkeypatch):
    """A run with --mcmc.noise-schedule linear: the strategy sees the linear rate at every step, and config.json
    keeps the ablation options."""
    seen: list[tuple[int, float]] = []
    original = MCMCStrategy.step_post_optimizer

    def spy(self, step, model, optimizers, means_lr):
        seen.append((step, means_lr))
        return original(self, step, model, optimizers, means_lr)

    monkeypatch.setattr(MCMCStrategy, "step_post_optimizer", spy)
    out = tmp_path / "run"
    assert main(["train", str(mini_demo), "--out", str(out), "--steps", "20", "--quiet", "--downscale", "4",
                 "--no-save-renders", "--mcmc.noise-schedule", "linear", "--mcmc.noise-all-params",
                 "--mcmc.no-noise-gated", "--mcmc.noise-lr", "5", "--model.num-init-points", "300"]) == 0
    config, plan = load_run_config(out / "config.json")  # what --resume and eval read back
    saved = config.mcmc
    assert (saved.noise_schedule, saved.noise_all_params, saved.noise_gated, saved.noise_lr) == ("linear", True,
                                                                                                  False, 5.0)
    assert saved.param_noise_decay == 0.9995, "the option as asked"
    assert plan.schedule.param_noise_decay == pytest.approx(0.9995 ** (30_000 / 20)), "fitted to 20 steps, in the plan"
    assert len(seen) == 20
    rates = [rate for _, rate in seen]
    steps_differences = [b - a for a, b in zip(rates, rates[1:])]
    assert steps_differences[0] < 0  # falling, along a straight line (the exponential's steps shrink)
    assert all(math.isclose(d, steps_differences[0], rel_tol=1e-6) for d in steps_differences)
