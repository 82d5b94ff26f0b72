"""One Adam per parameter, the position LR schedule, and the row surgery helpers (mcsplat.optim)."""

from __future__ import annotations

import io
import math

import pytest
import torch

from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import (OptimConfig, append_rows, copy_rows, make_optimizers, means_lr_at, remove_rows,
                           set_means_lr, set_rows, zero_moments)
from tests.support.helpers import random_adam_step

RADIUS = 3.0


def random_model(n: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.empty(n)
    with torch.no_grad():
        for key in PARAM_KEYS:
            model.params[key].copy_(torch.randn(model.params[key].shape, generator=g))
    return model


def moments(optimizers, key):
    state = optimizers[key].state[optimizers[key].param_groups[0]["params"][0]]
    return state["exp_avg"], state["exp_avg_sq"], state["step"]


def test_make_optimizers_follows_spec_section_8():
    model = random_model(10)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    assert set(optimizers) == set(PARAM_KEYS)
    expected = {"means": 1.6e-4 * RADIUS, "sh0": 2.5e-3, "shN": 2.5e-3 / 20, "opacity_logits": 0.05,
                "log_scales": 5e-3, "quats": 1e-3}
    for key, opt in optimizers.items():
        assert isinstance(opt, torch.optim.Adam)
        (group,) = opt.param_groups
        assert group["params"] == [model.params[key]] and group["params"][0] is model.params[key]
        assert group["lr"] == pytest.approx(expected[key])
        assert group["eps"] == 1e-15 and tuple(group["betas"]) == (0.9, 0.999)


def test_means_lr_schedule_is_log_linear():
    config = OptimConfig()
    assert means_lr_at(0, 30_000, config, RADIUS) == pytest.approx(1.6e-4 * RADIUS)
    assert means_lr_at(30_000, 30_000, config, RADIUS) == pytest.approx(1.6e-6 * RADIUS)
    assert means_lr_at(99_999, 30_000, config, RADIUS) == pytest.approx(1.6e-6 * RADIUS)  # held after the end
    assert means_lr_at(15_000, 30_000, config, RADIUS) == pytest.approx(1.6e-5 * RADIUS)  # geometric mean
    # gsplat's ExponentialLR: lr0 * 0.01^(k / max_steps)
    for k in (1, 777, 12_345):
        assert means_lr_at(k, 30_000, config, RADIUS) == pytest.approx(1.6e-4 * RADIUS * 0.01 ** (k / 30_000))
    optimizers = make_optimizers(random_model(3), config, RADIUS)
    set_means_lr(optimizers, 1.25e-5)
    assert optimizers["means"].param_groups[0]["lr"] == 1.25e-5
    assert optimizers["quats"].param_groups[0]["lr"] == 1e-3


def test_append_rows_extends_params_and_state_with_zero_moments():
    model = random_model(20)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    random_adam_step(model, optimizers, seed=1)
    before = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    old_moments = {k: tuple(t.clone() for t in moments(optimizers, k)) for k in PARAM_KEYS}
    rows = {k: torch.randn((4,) + before[k].shape[1:]) for k in PARAM_KEYS}
    append_rows(model, optimizers, rows)
    assert model.num_gaussians == 24
    for key in PARAM_KEYS:
        param = model.params[key]
        assert optimizers[key].param_groups[0]["params"][0] is param  # the optimizer holds the new Parameter
        assert param.requires_grad and param.grad is None
        assert torch.equal(param[:20].detach(), before[key]) and torch.equal(param[20:].detach(), rows[key])
        exp_avg, exp_avg_sq, step = moments(optimizers, key)
        assert exp_avg.shape == param.shape and exp_avg_sq.shape == param.shape
        assert torch.equal(exp_avg[:20], old_moments[key][0]) and torch.equal(exp_avg_sq[:20], old_moments[key][1])
        assert torch.count_nonzero(exp_avg[20:]) == 0 and torch.count_nonzero(exp_avg_sq[20:]) == 0
        assert torch.equal(step, old_moments[key][2])
    random_adam_step(model, optimizers, seed=2)  # the optimizers keep working


def test_surgery_leaves_the_old_rows_on_the_same_trajectory():
    """Appending then removing rows does not perturb the Adam trajectory of the other rows."""
    plain, edited = random_model(15, seed=3), random_model(15, seed=3)
    opt_plain = make_optimizers(plain, OptimConfig(), RADIUS)
    opt_edited = make_optimizers(edited, OptimConfig(), RADIUS)
    for seed in range(3):
        random_adam_step(plain, opt_plain, seed)
        random_adam_step(edited, opt_edited, seed)
    append_rows(edited, opt_edited, {k: torch.ones((5,) + plain.params[k].shape[1:]) for k in PARAM_KEYS})
    mask = torch.zeros(20, dtype=torch.bool)
    mask[15:] = True
    remove_rows(edited, opt_edited, mask)
    for seed in range(3, 6):
        random_adam_step(plain, opt_plain, seed)
        random_adam_step(edited, opt_edited, seed)
    for key in PARAM_KEYS:
        assert torch.equal(plain.params[key], edited.params[key])


def test_remove_rows_by_mask():
    model = random_model(12)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    random_adam_step(model, optimizers, seed=4)
    mask = torch.tensor([i % 3 == 0 for i in range(12)])
    before = {k: model.params[k].detach().clone() for k in PARAM_KEYS}
    old = {k: moments(optimizers, k)[0].clone() for k in PARAM_KEYS}
    remove_rows(model, optimizers, mask)
    assert model.num_gaussians == 8
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key].detach(), before[key][~mask])
        assert torch.equal(moments(optimizers, key)[0], old[key][~mask])
        assert optimizers[key].param_groups[0]["params"][0] is model.params[key]
    remove_rows(model, optimizers, torch.zeros(8, dtype=torch.bool))  # no-op
    assert model.num_gaussians == 8
    with pytest.raises(ValueError, match="boolean mask"):
        remove_rows(model, optimizers, torch.tensor([0, 1]))


def test_copy_set_and_zero_moments_at_indices():
    model = random_model(10)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    random_adam_step(model, optimizers, seed=5)
    params_before = {k: model.params[k] for k in PARAM_KEYS}
    state_before = {k: tuple(t.clone() for t in moments(optimizers, k)) for k in PARAM_KEYS}
    copy_rows(model, torch.tensor([0, 1]), torch.tensor([7, 8]))
    for key in PARAM_KEYS:
        assert model.params[key] is params_before[key]  # in place
        assert torch.equal(model.params[key][7], model.params[key][0])
        assert torch.equal(model.params[key][8], model.params[key][1])
        assert torch.equal(moments(optimizers, key)[0], state_before[key][0])  # state untouched
    set_rows(model, torch.tensor([2, 3]), {"opacity_logits": torch.tensor([5.0, -5.0])})
    assert model.params["opacity_logits"][2] == 5.0 and model.params["opacity_logits"][3] == -5.0

    zero_moments(optimizers, torch.tensor([1, 4, 4]))
    for key in PARAM_KEYS:
        exp_avg, exp_avg_sq, step = moments(optimizers, key)
        zeroed = torch.zeros(10, dtype=torch.bool)
        zeroed[[1, 4]] = True
        assert torch.count_nonzero(exp_avg[zeroed]) == 0 and torch.count_nonzero(exp_avg_sq[zeroed]) == 0
        assert torch.equal(exp_avg[~zeroed], state_before[key][0][~zeroed])
        assert torch.equal(exp_avg_sq[~zeroed], state_before[key][1][~zeroed])
        assert torch.equal(step, state_before[key][2])
    zero_moments(optimizers, torch.tensor([0]), keys=("opacity_logits",))
    assert moments(optimizers, "opacity_logits")[0][0] == 0
    assert moments(optimizers, "means")[0][0].abs().sum() > 0


def test_helpers_work_before_the_first_step():
    model = random_model(5)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    zero_moments(optimizers, torch.tensor([0, 1]))
    append_rows(model, optimizers, {k: torch.zeros((2,) + model.params[k].shape[1:]) for k in PARAM_KEYS})
    remove_rows(model, optimizers, torch.tensor([True, False, False, False, False, False, True]))
    assert model.num_gaussians == 5
    random_adam_step(model, optimizers, seed=6)
    assert moments(optimizers, "means")[0].shape == (5, 3)


def test_optimizer_state_survives_the_checkpoint_round_trip_after_surgery():
    model = random_model(8)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    random_adam_step(model, optimizers, seed=7)
    append_rows(model, optimizers, {k: torch.randn((3,) + model.params[k].shape[1:]) for k in PARAM_KEYS})
    random_adam_step(model, optimizers, seed=8)
    buffer = io.BytesIO()  # through torch.save: state_dict()s share memory with the live tensors
    torch.save({"model": model.state_dict(), "optim": {k: o.state_dict() for k, o in optimizers.items()}}, buffer)
    buffer.seek(0)
    checkpoint = torch.load(buffer)

    restored = GaussianModel.from_state_dict(checkpoint["model"])
    restored_opt = make_optimizers(restored, OptimConfig(), RADIUS)
    for key, opt in restored_opt.items():
        opt.load_state_dict(checkpoint["optim"][key])
    for key in PARAM_KEYS:
        for a, b in zip(moments(optimizers, key), moments(restored_opt, key)):
            assert torch.equal(a, b)
    random_adam_step(model, optimizers, seed=9)
    random_adam_step(restored, restored_opt, seed=9)
    for key in PARAM_KEYS:
        assert torch.equal(model.params[key], restored.params[key])


@pytest.mark.parametrize("field", ["means_lr", "sh0_lr", "shN_lr", "opacity_lr", "scales_lr", "quats_lr",
                                   "means_lr_final", "eps"])
def test_negative_learning_rates_raise(field):
    with pytest.raises(ValueError, match=field):
        OptimConfig(**{field: -1.0})


def test_other_impossible_options_raise():
    with pytest.raises(ValueError, match="betas"):
        OptimConfig(betas=(0.9, 1.0))
    with pytest.raises(ValueError, match="means_lr_final"):
        OptimConfig(means_lr_final=0.0)
    with pytest.raises(ValueError, match="max_steps"):
        means_lr_at(0, 0, OptimConfig(), RADIUS)
    with pytest.raises(ValueError, match="scene_radius"):
        make_optimizers(random_model(2), OptimConfig(), -1.0)
    with pytest.raises(ValueError, match="learning rate"):
        set_means_lr(make_optimizers(random_model(2), OptimConfig(), 1.0), math.nan)
    assert means_lr_at(5, 10, OptimConfig(means_lr=0.0), RADIUS) == 0.0
