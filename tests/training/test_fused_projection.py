"""The fused update (optim/fused_projection.py: the projection's backward applies Adam, one pass over the Gaussians)
gives the plain update's result to the bit: the plain one lets autograd finish the projection's gradients and steps
torch's fused Adam (through adam_cpu, itself torch's to the bit: test_adam_cpu.py), whose gradients the float64 checks
of test_project_simd.py hold. Over steps with regularizers on the scales and opacities, every SH degree, changing
learning rates and row surgery between the steps; where it cannot apply (a camera being refined, a second render, an
optimizer the kernel does not take) it finishes the gradients and steps as the plain update does; where more terms
than one add to the projection's parameters (a normal map, a second render), the same to float32 rounding."""

from __future__ import annotations

import pytest
import torch

from mcsplat import adam_cpu, render
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import (OptimConfig, PlainUpdate, append_rows, make_optimizers, remove_rows, set_means_lr,
                           update_for, zero_moments)
from mcsplat.optim import fused_projection, fused_projection_warp
from mcsplat.optim.fused_projection import FusedProjectionAdam
from mcsplat.render import set_cpu_threads
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.render.project import deferred
from mcsplat.strategy.base import l1_regularizers

from tests.render.test_render import make_camera
from tests.training.test_adam_cpu import assert_identical

pytestmark = pytest.mark.skipif(not adam_cpu.matches_torch(), reason="torch's CPU kernels here are not those the "
                                "CPU's Adam reproduces (the fused update is not chosen)")


def scene(n: int, seed: int) -> GaussianModel:
    """Gaussians in front of, around and behind the camera; n odd leaves every tensor a remainder past 16 and 8."""
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.empty(n, sh_degree=3)
    with torch.no_grad():
        model.params["means"].copy_((torch.rand(n, 3, generator=g) - 0.5) * 4.0)
        model.params["log_scales"].copy_(-4.0 + 3.0 * torch.rand(n, 3, generator=g))
        model.params["quats"].copy_(torch.randn(n, 4, generator=g))
        model.params["opacity_logits"].copy_(torch.randn(n, generator=g))
        model.params["sh0"].copy_(torch.randn(n, 1, 3, generator=g))
        model.params["shN"].copy_(0.3 * torch.randn(n, 15, 3, generator=g))
    return model


def twins(n: int, seed: int):
    models = scene(n, seed), scene(n, seed)
    return [(model, make_optimizers(model, OptimConfig(), scene_radius=2.0)) for model in models]


def train_step(model, optimizers, update, camera, sh_degree: int, seed: int, renders: int = 1,
               normals: bool = False) -> None:
    """A render (or several, summed) with a random linear loss of its colours and depth (and its normal map, which
    reads the scales and rotations in torch: --surface's), MCMC's two regularizers after them, as the step adds them
    (the fused update takes their gradients too)."""
    g = torch.Generator().manual_seed(seed)
    loss = 0.0
    with update.rendering(model):
        for _ in range(renders):
            result = render.render(model, camera, (0.1, 0.2, 0.3), sh_degree, outputs=("normals",) if normals else ())
            loss = loss + (result.rgb * weights_like(result.rgb, g)).sum()
            loss = loss + 0.1 * (result.depth * weights_like(result.depth, g)).sum()
            if normals:
                loss = loss + (result.normal * weights_like(result.normal, g)).sum()
        loss = loss + l1_regularizers(model, 0.01, 0.02)
    loss.backward()
    update.step(optimizers)


def weights_like(tensor: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    return torch.randn(tensor.shape, generator=generator).to(tensor.device)


def counted_fused_updates(monkeypatch) -> list[int]:
    calls: list[int] = []
    fused = fused_projection.update
    monkeypatch.setattr(fused_projection, "update", lambda *a, **k: (calls.append(1), fused(*a, **k)))
    return calls


def counted_regularizers_left(monkeypatch) -> list[bool]:
    left: list[bool] = []
    take = deferred.regularizers_left_to_update
    monkeypatch.setattr(deferred, "regularizers_left_to_update",
                        lambda *a: (lambda value: (left.append(value is not None), value)[1])(take(*a)))
    return left


def test_the_fused_update_is_the_plain_update_to_the_bit_through_steps_and_row_surgery(monkeypatch):
    calls = counted_fused_updates(monkeypatch)
    left = counted_regularizers_left(monkeypatch)
    (plain, plain_opt), (fused, fused_opt) = twins(4001, seed=3)
    camera = make_camera(width=70, height=50, distance=3.0)
    updates = PlainUpdate(), FusedProjectionAdam()
    set_cpu_threads(2, split_small_work=True)
    try:
        for step in range(8):
            for (model, optimizers), update in zip(((plain, plain_opt), (fused, fused_opt)), updates):
                set_means_lr(optimizers, 1e-3 * 0.8 ** step)
                train_step(model, optimizers, update, camera, sh_degree=min(step // 2, 3), seed=step)
                if step == 2:  # growth, relocation's moment reset, pruning: the state moves with the rows
                    g = torch.Generator().manual_seed(7)
                    append_rows(model, optimizers, {key: torch.randn((37, *model.params[key].shape[1:]),
                                                                     generator=g) for key in PARAM_KEYS})
                    zero_moments(optimizers, torch.arange(0, 4000, 3))
                if step == 5:
                    remove_rows(model, optimizers, torch.arange(model.num_gaussians) % 5 == 1)
            assert_identical(plain, fused, plain_opt, fused_opt)
    finally:
        set_cpu_threads(None)
    assert len(calls) == 8  # the fused kernel took every step
    assert left == [False, True] * 8  # and the regularizers' gradients, which the plain twin's autograd took


def test_where_it_cannot_fuse_it_steps_as_the_plain_update(monkeypatch):
    calls = counted_fused_updates(monkeypatch)
    camera = make_camera(width=40, height=30, distance=3.0)
    # A second render in one step (the first defers, the second backs up as usual), or a normal map in the loss:
    # three gradients of a parameter sum in another order than autograd's, the same to float32 rounding.
    for case in ({"renders": 2}, {"normals": True}):
        (plain, plain_opt), (fused, fused_opt) = twins(301, seed=5)
        train_step(plain, plain_opt, PlainUpdate(), camera, 3, seed=0, **case)
        train_step(fused, fused_opt, FusedProjectionAdam(), camera, 3, seed=0, **case)
        for key in PARAM_KEYS:
            a, b = plain.params[key], fused.params[key]
            torch.testing.assert_close(a, b, rtol=0, atol=1e-7)  # Adam's first step: the learning rate times the sign
            for name in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(plain_opt[key].state[a][name], fused_opt[key].state[b][name], rtol=1e-5,
                                           atol=1e-12)
    assert len(calls) == 2
    # Optimizers the kernel does not take (torch's for-loop Adam): the deferred gradients are finished into .grad.
    (plain, _), (fused, _) = twins(301, seed=6)
    plain_opt, fused_opt = ({key: torch.optim.Adam([m.params[key]], lr=1e-3, foreach=False) for key in PARAM_KEYS}
                            for m in (plain, fused))
    for step in range(3):
        train_step(plain, plain_opt, PlainUpdate(), camera, 3, seed=step)
        train_step(fused, fused_opt, FusedProjectionAdam(), camera, 3, seed=step)
    assert_identical(plain, fused, plain_opt, fused_opt)
    assert len(calls) == 2
    # A camera being refined needs the view's gradient within autograd's pass: nothing is deferred.
    (plain, plain_opt), (fused, fused_opt) = twins(301, seed=8)
    views = []
    for model, optimizers, update in ((plain, plain_opt, PlainUpdate()), (fused, fused_opt, FusedProjectionAdam())):
        moving = make_camera(width=40, height=30, distance=3.0)
        moving.world_to_camera.requires_grad_()
        train_step(model, optimizers, update, moving, 3, seed=0)
        views.append(moving.world_to_camera.grad)
    assert_identical(plain, fused, plain_opt, fused_opt)
    assert torch.equal(views[0], views[1]) and len(calls) == 2


def test_the_fused_update_is_chosen_for_one_process_on_the_cpu():
    assert isinstance(update_for(torch.device("cpu")), FusedProjectionAdam)
    assert isinstance(update_for(torch.device("cpu"), processes=2), PlainUpdate)
    assert isinstance(update_for(torch.device("cuda")), PlainUpdate)


def test_the_warp_kernels_fused_update_is_the_plain_update_to_float32_rounding(monkeypatch, device):
    """The projection's Warp kernels (CUDA's; on the CPU the scalar kernels): the fused Warp kernel, its gradient rows
    kept across steps and made again as the model grows and shrinks."""
    calls: list[int] = []
    fused = fused_projection_warp.update
    monkeypatch.setattr(fused_projection_warp, "update", lambda *a, **k: (calls.append(1), fused(*a, **k)))
    models = scene(1001, 4).to(device), scene(1001, 4).to(device)
    (plain, plain_opt), (fused_model, fused_opt) = [(m, make_optimizers(m, OptimConfig(), scene_radius=2.0))
                                                    for m in models]
    camera = make_camera(width=70, height=50, distance=3.0).to(device)
    updates = PlainUpdate(), FusedProjectionAdam()
    set_cpu_kernels("scalar")
    try:
        for step in range(5):
            for (model, optimizers), update in zip(((plain, plain_opt), (fused_model, fused_opt)), updates):
                train_step(model, optimizers, update, camera, sh_degree=min(step, 3), seed=step)
                if step == 1:
                    g = torch.Generator().manual_seed(9)
                    append_rows(model, optimizers, {key: torch.randn((21, *model.params[key].shape[1:]),
                                                                     generator=g).to(device) for key in PARAM_KEYS})
                if step == 3:
                    remove_rows(model, optimizers, torch.arange(model.num_gaussians, device=device) % 4 == 1)
    finally:
        set_cpu_kernels("simd")
    assert len(calls) == 5
    for key in PARAM_KEYS:
        a, b = plain.params[key], fused_model.params[key]
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
        for name in ("exp_avg", "exp_avg_sq"):  # near zero, a moment is a difference of rounded terms
            ours, torchs = fused_opt[key].state[b][name], plain_opt[key].state[a][name]
            torch.testing.assert_close(ours, torchs, rtol=1e-4, atol=1e-5 * float(torchs.abs().max()))


def test_the_fused_warp_kernel_compiles_for_hopper_gpus_without_one(tmp_path):
    """Warp's NVRTC compiles the fused update's kernel for sm_90 (H100 / H200) on a machine with no GPU (to PTX: half
    the time of a cubin, and the CUDA source is what could fail here)."""
    import warp as wp

    from mcsplat.compute.runtime import ensure_warp

    ensure_warp()
    module = fused_projection_warp.fused_kernel(wp.float32).module
    (ptx,) = wp.compile_aot_module(module, arch=90, module_dir=tmp_path, use_ptx=True)
    assert ptx.suffix == ".ptx" and "project_backward_adam" in ptx.read_text()
