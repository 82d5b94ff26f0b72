"""The CPU's fused Adam (mcsplat.adam_cpu through optim.step_optimizers) gives torch.optim.Adam's result to the bit:
over steps with the position learning rate's schedule, row surgery between them, a checkpoint's round trip and
parameters left without a gradient."""

from __future__ import annotations

import io

import pytest
import torch

from mcsplat import adam_cpu
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import (OptimConfig, append_rows, copy_rows, make_optimizers, means_lr_at, remove_rows,
                           set_means_lr, step_optimizers, zero_moments)

pytestmark = pytest.mark.skipif(not adam_cpu.matches_torch(), reason="torch's CPU kernels here are not those the "
                                "fused Adam reproduces (x86 AVX-512 or AVX2): optim.step_optimizers uses torch's own")
RADIUS = 2.5


def twins(n: int, sh_degree: int = 3) -> tuple[GaussianModel, GaussianModel]:
    """Two identical models; their sizes leave every tensor a remainder past a multiple of 16 and of 8 (n odd)."""
    pair = GaussianModel.empty(n, sh_degree=sh_degree), GaussianModel.empty(n, sh_degree=sh_degree)
    g = torch.Generator().manual_seed(n)
    with torch.no_grad():
        for key in PARAM_KEYS:
            values = torch.randn(pair[0].params[key].shape, generator=g)
            for model in pair:
                model.params[key].copy_(values)
    return pair


def set_gradients(model: GaussianModel, seed: int, skip: tuple[str, ...] = ()) -> None:
    """Gradients of a few orders of magnitude (some exactly zero), the same for a given seed."""
    g = torch.Generator().manual_seed(seed)
    for key in PARAM_KEYS:
        param = model.params[key]
        grad = torch.randn(param.shape, generator=g) * 10.0 ** torch.randint(-7, 2, param.shape, generator=g)
        grad[torch.rand(param.shape, generator=g) < 0.05] = 0.0
        param.grad = None if key in skip else grad


def torch_step(optimizers) -> None:
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)


def assert_identical(a: GaussianModel, b: GaussianModel, opt_a, opt_b) -> None:
    for key in PARAM_KEYS:
        assert torch.equal(a.params[key], b.params[key]), key
        state_a, state_b = opt_a[key].state[a.params[key]], opt_b[key].state[b.params[key]]
        assert state_a.keys() == state_b.keys(), key
        for name in state_a:
            assert torch.equal(state_a[name], state_b[name]), (key, name)
            assert state_a[name].dtype == state_b[name].dtype, (key, name)


def test_the_steps_and_row_surgery_match_torch_adam_bit_for_bit(monkeypatch):
    launches = []
    fused = adam_cpu.adam_step
    monkeypatch.setattr(adam_cpu, "adam_step", lambda **tensors: (launches.append(1), fused(**tensors)))
    ours, theirs = twins(501)
    config = OptimConfig()
    opt_ours, opt_theirs = make_optimizers(ours, config, RADIUS), make_optimizers(theirs, config, RADIUS)
    for step in range(9):
        for model, optimizers, take in ((ours, opt_ours, step_optimizers), (theirs, opt_theirs, torch_step)):
            set_means_lr(optimizers, means_lr_at(step, 9, config, RADIUS))
            set_gradients(model, step)
            take(optimizers)
            assert all(p.grad is None for p in model.params.values())
            if step == 2:
                rows = {key: torch.full((37,) + model.params[key].shape[1:], 0.5) for key in PARAM_KEYS}
                append_rows(model, optimizers, rows)  # new rows' moments zero, counters as they were
            if step == 4:
                zero_moments(optimizers, torch.tensor([0, 3, 100]))
                copy_rows(model, torch.tensor([1, 2]), torch.tensor([5, 6]))
            if step == 6:
                mask = torch.zeros(model.num_gaussians, dtype=torch.bool)
                mask[::7] = True
                remove_rows(model, optimizers, mask)
        assert_identical(ours, theirs, opt_ours, opt_theirs)
    assert ours.num_gaussians == 538 - len(range(0, 538, 7))
    assert opt_ours["means"].state[ours.means]["step"].item() == 9.0
    assert len(launches) == 9, "one launch a step for all six parameters"


def test_a_checkpoint_of_either_continues_the_same_in_the_other():
    ours, theirs = twins(77, sh_degree=0)
    opt_ours, opt_theirs = make_optimizers(ours, OptimConfig(), RADIUS), make_optimizers(theirs, OptimConfig(), RADIUS)
    for seed in range(3):
        set_gradients(ours, seed), set_gradients(theirs, seed)
        step_optimizers(opt_ours), torch_step(opt_theirs)
    # Each side's checkpoint is loaded by the other, which steps on.
    saved_ours = {k: torch.load(io.BytesIO(_bytes(o.state_dict())), weights_only=True) for k, o in opt_ours.items()}
    saved_theirs = {k: torch.load(io.BytesIO(_bytes(o.state_dict())), weights_only=True)
                    for k, o in opt_theirs.items()}
    for key in PARAM_KEYS:
        opt_ours[key].load_state_dict(saved_theirs[key])
        opt_theirs[key].load_state_dict(saved_ours[key])
    for seed in range(3, 6):
        set_gradients(ours, seed), set_gradients(theirs, seed)
        step_optimizers(opt_ours), torch_step(opt_theirs)
    assert_identical(ours, theirs, opt_ours, opt_theirs)


def _bytes(state: dict) -> bytes:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def test_a_parameter_without_gradient_takes_no_step_as_in_torch():
    ours, theirs = twins(40, sh_degree=1)
    opt_ours, opt_theirs = make_optimizers(ours, OptimConfig(), RADIUS), make_optimizers(theirs, OptimConfig(), RADIUS)
    for seed in range(4):
        skip = ("shN",) if seed < 2 else ("opacity_logits",)
        set_gradients(ours, seed, skip), set_gradients(theirs, seed, skip)
        step_optimizers(opt_ours), torch_step(opt_theirs)
    assert_identical(ours, theirs, opt_ours, opt_theirs)
    assert opt_ours["shN"].state[ours.params["shN"]]["step"].item() == 2.0


def test_an_optimizer_the_kernel_does_not_take_steps_itself():
    """amsgrad, a non-fused Adam and another optimizer class: their own step(), gradients dropped as before."""
    params = [torch.nn.Parameter(torch.randn(33)) for _ in range(6)]
    copies = [torch.nn.Parameter(p.detach().clone()) for p in params]

    def optimizers(ps):
        return {"amsgrad": torch.optim.Adam([ps[0]], lr=0.1, amsgrad=True, fused=True),
                "plain": torch.optim.Adam([ps[1]], lr=0.1), "sgd": torch.optim.SGD([ps[2]], lr=0.1),
                "fused": torch.optim.Adam(ps[3:], lr=0.01, eps=1e-15, fused=True)}

    ours, theirs = optimizers(params), optimizers(copies)
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        for p, q in zip(params, copies):
            p.grad = torch.randn(33, generator=g)
            q.grad = p.grad.clone()
        step_optimizers(ours), torch_step(theirs)
    assert all(torch.equal(p, q) and p.grad is None for p, q in zip(params, copies))
