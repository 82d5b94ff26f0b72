"""A training step reads nothing back from the device and copies nothing to it in a way that waits, so that a GPU's
queue never waits for the host and the step can be captured as a CUDA graph. Checked on the CPU through a device that
refuses reads (tests/support/device_reads.py), with the Warp kernels CUDA runs (set_cpu_kernels("scalar")): the loss
and PSNR stay on the device until read, whether the loss stayed finite is read every few steps, the pair lists go
into a room sized ahead (render/bin/pair_room.py), the strategy's per-step statistics are dense, a view's camera and
the background are moved to the device once, the image without waiting."""

from __future__ import annotations

import contextlib

import pytest
import torch
import warp as wp

from mcsplat import render
from mcsplat.compute.runtime import array_t
from mcsplat.config import config_of
from mcsplat.data import load_scene
from mcsplat.errors import MCSplatError
from mcsplat.gaussians import GaussianModel
from mcsplat.loss_terms import standard_terms
from mcsplat.optim import PlainUpdate, make_optimizers
from mcsplat.optim.fused_projection import FusedProjectionAdam
from mcsplat.planning import Plan
from mcsplat.planning.strategy_choice import make_strategy
from mcsplat.render.bin import pair_room
from mcsplat.render import set_cpu_threads
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.run.scene import background_of
from mcsplat.step import Step
from mcsplat.surface_terms import surface_terms

from tests.support.device_reads import DeviceRead, RefuseReads

CPU = torch.device("cpu")


@pytest.fixture
def warp_kernels():
    """The Warp kernels CUDA runs, on the CPU, and rooms made afresh."""
    pair_room.forget_rooms()
    set_cpu_kernels("scalar")
    yield
    set_cpu_kernels("simd")
    pair_room.forget_rooms()


def run_step(scene, strategy="mcmc", update=None, surface=False, device=CPU):
    config = config_of(data=scene.root, steps=1000, strategy=strategy, surface=surface, surface_from=0.0)
    plan = Plan.literal(config)
    model = GaussianModel.random_init(scene.radius, blender=True, num_points=2000,
                                      generator=torch.Generator().manual_seed(0)).to(device)
    strategy = make_strategy(config, plan, scene.radius, torch.Generator(device).manual_seed(0))
    terms = None  # the standard ones
    if surface:  # and --surface's, the normal term on from the first step
        terms = standard_terms(config.ssim_weight, strategy, ()) + surface_terms(100.0, 0.015, 0.0, scene.radius)
    step = Step(model, make_optimizers(model, plan.optim, scene.radius), strategy, config, scene.radius,
                background_of(config, scene), device, update=update or PlainUpdate(), loss_terms=terms)
    return step, plan


@contextlib.contextmanager
def refusing_reads(device: torch.device, host: list[torch.Tensor]):
    """On the CPU the torch mode of tests/support/device_reads.py; on a GPU the device itself: torch's sync debug
    mode makes every wait for the GPU an error."""
    if device.type != "cuda":
        with RefuseReads(host=host) as reads:
            yield reads
        return
    torch.cuda.set_sync_debug_mode("error")
    try:
        yield None
    finally:
        torch.cuda.set_sync_debug_mode("default")


@pytest.mark.parametrize("strategy, update, surface", [("mcmc", PlainUpdate, False), ("adc", PlainUpdate, False),
                                                       ("mcmc", FusedProjectionAdam, False),
                                                       ("mcmc", PlainUpdate, True)])
def test_a_training_step_reads_nothing_back(mini_demo, warp_kernels, strategy, update, surface, device):
    """With the plain update (torch's Adam steps the parameters), with the Warp kernel's fused update, and with
    --surface's terms (its normal map and planar depth a second compositing pass); on a GPU (pytest --device cuda)
    under torch's sync debug mode."""
    scene = load_scene(mini_demo, downscale=4)
    step, plan = run_step(scene, strategy, update(), surface, device)
    views = scene.train[:3]
    for index, view in enumerate(views):  # each view's camera numbers are read once, from host memory; the room made
        step(index, view, plan, index)
    (room,) = pair_room._rooms.values()
    results = []
    with refusing_reads(device, host=[room.host_copy()]) as reads:
        for index in range(3, 9):
            results.append(step(index, views[index % 3], plan, index % 3))
    assert reads is None or reads.host_reads == 6  # each render the room's copy of the last count (sent by then)
    losses = [result.loss for result in results]  # read now, after the steps
    assert all(0 < loss < 1 for loss in losses) and all(result.train_psnr > 5 for result in results)
    step.check_finite()
    assert room.overflows == 0


def test_the_refusing_device_catches_what_a_step_used_to_read(mini_demo, warp_kernels):
    """The check can fail: a render outside a training step reads its pair count, as every render did; Python
    numbers made into a tensor on a device are an upload that waits."""
    scene = load_scene(mini_demo, downscale=4)
    step, plan = run_step(scene)
    camera = scene.train[0].camera_at(1.0)
    camera.pose_numbers, camera.focal_and_centre  # read once from host memory, as a step's camera is
    with RefuseReads(), pytest.raises(DeviceRead, match="__int__"):
        render.render(step.model, camera, torch.zeros(3), 0)
    with RefuseReads(), pytest.raises(DeviceRead, match="item"):
        torch.ones(3).sum().item()
    with RefuseReads(), pytest.raises(DeviceRead, match="copies to a device"):
        torch.tensor([0.5, 0.5], device=CPU)
    host = scene.train[6].camera_at(1.0)
    moved = host.to("meta")  # another device (no GPU here): a view's camera is moved once, then kept
    assert moved.K.device.type == "meta" and host.to("meta") is moved
    assert host.to(CPU) is not host.to(CPU)  # on its own device nothing is copied, nor kept


def test_a_loss_that_stopped_being_finite_is_named_at_its_step_when_read(mini_demo, warp_kernels, monkeypatch):
    from mcsplat import step as step_module

    scene = load_scene(mini_demo, downscale=4)
    one_step, plan = run_step(scene)
    real = step_module.total_loss
    monkeypatch.setattr(step_module, "total_loss", lambda terms, context: real(terms, context) * (
        float("nan") if context.step == 12 else 1.0))
    for index in range(10, 15):
        one_step(index, scene.train[0], plan)
    with pytest.raises(MCSplatError, match="step 12: the loss became nan"):
        one_step.check_finite()


def launches_of(step, plan, view, index: int) -> list[tuple]:
    """The Warp launches of one step: each kernel, its size and its arguments (numbers as they are, arrays by shape)."""
    made = []

    def recording(kernel, dim, inputs=(), **options):
        made.append((kernel.key, dim, tuple(("array", tuple(a.shape)[:a.ndim]) if isinstance(a, array_t) else
                                            ("array", tuple(a.shape)) if isinstance(a, wp.array) else a
                                            for a in inputs)))
        return launch(kernel, dim=dim, inputs=inputs, **options)

    launch = wp.launch
    wp.launch = recording
    try:
        step(index, view, plan, 0)
    finally:
        wp.launch = launch
    return made


def test_a_step_launches_the_same_kernels_with_the_same_arguments_from_view_to_view(mini_demo, warp_kernels):
    """What a CUDA graph needs of the step: its kernels, their sizes and their numbers do not change with the view
    (the camera comes as an array, warp_kernel.packed_camera; the pair lists' room has a size known ahead). Only
    the arrays' contents differ, and on the CPU their addresses."""
    scene = load_scene(mini_demo, downscale=4)
    step, plan = run_step(scene)
    set_cpu_threads(1)  # the launches in one order (a thread pool's workers would launch their ranges in any)
    try:
        for index, view in enumerate(scene.train[:3]):
            step(index, view, plan, index)
        first, second = (launches_of(step, plan, scene.train[k], 3 + k) for k in (0, 1))
    finally:
        set_cpu_threads(None)
    assert [launch[0] for launch in first][:2] == ["projection_kernels__locals__project", "_count_pairs"]
    assert len(first) >= 8 and first == second
