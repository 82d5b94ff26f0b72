"""A training step replayed as a CUDA graph (graphed_step.py), checked on the CPU: a recorder stands in for the graph
(tests/support/graph_check.py) and checks at each replay that the step launched the same kernels and operators, with
the same numbers, on the same memory as at its capture. This is what a graph replays. The replayed run must also
train exactly as the step run as it is does, and read nothing back. On a GPU the graph itself waits for
benchmarks/gpu_session.py."""

from __future__ import annotations

import contextlib
import dataclasses

import pytest
import torch

from mcsplat.config import config_of
from mcsplat.data import load_scene
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.optim import make_optimizers
from mcsplat.planning import Plan
from mcsplat.planning.strategy_choice import make_strategy
from mcsplat.render import set_cpu_threads
from mcsplat.render.bin import pair_room
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.run.scene import background_of
from mcsplat import step as step_module
from mcsplat.step import Step
from mcsplat.graphed_step import WARM_STEPS, CaptureFailed, GraphedStep, graphed, not_replayable

from tests.support.device_reads import RefuseReads
from tests.support.graph_check import NotReplayable, ReplayRecorder, record


@pytest.fixture
def warp_kernels():
    """The Warp kernels CUDA runs, on the CPU, one thread (the launches in one order), rooms made afresh."""
    pair_room.forget_rooms()
    set_cpu_kernels("scalar")
    set_cpu_threads(1)
    yield
    set_cpu_threads(None)
    set_cpu_kernels("simd")
    pair_room.forget_rooms()


def mcmc_step(scene, device: torch.device = torch.device("cpu"), steps: int = 1000) -> tuple[Step, Plan]:
    """MCMC with a cap of 2,200 from 2,000 Gaussians, on the paper's schedules (the first refine step is 500)."""
    config = config_of(data=scene.root, steps=steps, cap_max=2200)
    plan = Plan.literal(config)
    model = GaussianModel.random_init(scene.radius, blender=True, num_points=2000,
                                      generator=torch.Generator().manual_seed(0)).to(device)
    strategy = make_strategy(config, plan, scene.radius, torch.Generator(device).manual_seed(0))
    return Step(model, make_optimizers(model, plan.optim, scene.radius), strategy, config, scene.radius,
                background_of(config, scene), device), plan


def test_a_replayed_step_trains_as_the_step_does_and_recaptures_after_growth(mini_demo, warp_kernels):
    scene = load_scene(mini_demo, downscale=4)
    alone, plan = mcmc_step(scene)
    recorder = ReplayRecorder()
    graphed = GraphedStep(mcmc_step(scene)[0], recorder)
    strategy = alone.strategy
    growth = next(step for step in range(8, 5000) if strategy.is_refine_step(step))
    steps = list(range(8)) + [growth] + list(range(growth + 1, growth + 4 + WARM_STEPS))
    room_copies: list[torch.Tensor] = []
    followed = {}  # the counts the room followed, by step
    for step in steps:
        view_index = step % 3
        view = scene.train[view_index]
        expected = alone(step, view, plan, view_index)
        if recorder.captures and not room_copies:
            room_copies.extend(room.host_copy() for room in pair_room._rooms.values())
        with RefuseReads(host=room_copies) if room_copies and step != growth else contextlib.nullcontext():
            got = graphed(step, view, plan, view_index)  # the growth step reads its counts, as it always has
        assert got.loss == expected.loss and got.train_psnr == expected.train_psnr, step
        followed[step] = len(next(iter(pair_room._rooms.values()))._ratios)
    # The room follows the replays' counts (told by the step, PairRoom.replayed: a graph runs none of its Python):
    # two a step, as the step run as it is renders at the same size into the same room
    assert followed[7] - followed[4] == 2 * 3
    # Step 0 before Adam has a state (a phase of its own), then warm steps, a capture, replays; the growth step as it
    # is (row surgery), then the grown model warms and is captured again
    assert recorder.captures == 2 and recorder.replays >= 3
    assert graphed.as_they_are >= 1 + WARM_STEPS + 1 + WARM_STEPS
    assert graphed.as_they_are + recorder.captures + recorder.replays == len(steps)
    assert alone.model.num_gaussians == graphed.step.model.num_gaussians > 2000
    for key in PARAM_KEYS:  # the same training to the bit: Adam's rates and the noise's from the device
        assert torch.equal(alone.model.params[key], graphed.step.model.params[key]), key
    graphed.check_finite()


def test_steps_a_graph_cannot_hold_run_as_they_are(mini_demo, warp_kernels):
    scene = load_scene(mini_demo, downscale=4)
    step, plan = mcmc_step(scene)
    step.strategy.config = dataclasses.replace(step.strategy.config, noise_all_params=True)
    recorder = ReplayRecorder()
    graphed = GraphedStep(step, recorder)
    for index in range(WARM_STEPS + 3):
        graphed(index, scene.train[0], plan)
    assert recorder.captures == 0 and graphed.as_they_are == WARM_STEPS + 3  # the noise's strength follows the step


class RefusingDevice(ReplayRecorder):
    def capture(self, work):
        raise CaptureFailed("operation not permitted when stream is capturing")


def test_a_step_the_device_cannot_capture_runs_as_it_is_and_the_run_goes_on(mini_demo, warp_kernels):
    scene = load_scene(mini_demo, downscale=4)
    alone, plan = mcmc_step(scene)
    graphed = GraphedStep(mcmc_step(scene)[0], RefusingDevice())
    for index in range(WARM_STEPS + 4):
        expected = alone(index, scene.train[index % 3], plan)
        if index == 1 + WARM_STEPS:  # the capture
            with pytest.warns(RuntimeWarning, match="could not be captured as a CUDA graph .* goes on without one"):
                got = graphed(index, scene.train[index % 3], plan)
        else:
            got = graphed(index, scene.train[index % 3], plan)
        assert got.loss == expected.loss
    assert graphed.failed and graphed.as_they_are == WARM_STEPS + 4


def test_the_recorder_catches_a_number_or_an_input_that_changes_between_replays(mini_demo, warp_kernels,
                                                                                 monkeypatch):
    """The check can fail: a learning rate given as a number (a graph would keep its first value), a rate or a
    tensor that is not in the capture's place (a graph would read the capture's)."""
    scene = load_scene(mini_demo, downscale=4)
    step, plan = mcmc_step(scene)
    recorder = ReplayRecorder()
    graphed = GraphedStep(step, recorder)
    group = step.optimizers["means"].param_groups[0]
    group["lr"] = float(group["lr"])  # undo rates_on_device for the positions (torch's Adam steps them, as on CUDA)
    group["capturable"] = True
    with pytest.raises(NotReplayable, match="_fused_adam"):
        for index in range(WARM_STEPS + 4):
            graphed(index, scene.train[0], plan)
    assert recorder.captures == 1
    set_means_lr = step_module.set_means_lr  # a rate put in a new tensor at each step: the graph reads the old one

    def in_a_new_tensor(optimizers, lr):
        optimizers["means"].param_groups[0]["lr"] = torch.tensor(lr, dtype=torch.float64)
    step, plan = mcmc_step(scene)
    graphed, recorder = GraphedStep(step, ReplayRecorder()), None
    monkeypatch.setattr(step_module, "set_means_lr", in_a_new_tensor)
    with pytest.raises(NotReplayable, match="kept.*\\(\\), \\(torch.float64"):
        for index in range(WARM_STEPS + 4):
            graphed(index, scene.train[0], plan)
    monkeypatch.setattr(step_module, "set_means_lr", set_means_lr)
    photos = [torch.ones(4), torch.ones(4)]
    recorder = ReplayRecorder()
    chosen = iter(photos + photos)
    recorder.capture(lambda: torch.add(next(chosen), 1))
    with pytest.raises(NotReplayable, match="kept"):
        recorder.replay()
    assert len(record(lambda: torch.ones(3) + 1)) == 2


def test_the_run_replays_its_step_only_where_asked_and_where_it_can(mini_demo):
    scene = load_scene(mini_demo, downscale=4)
    step, plan = mcmc_step(scene)
    assert graphed(step, False) is step
    with pytest.warns(RuntimeWarning, match="cannot be replayed as a CUDA graph on the CPU; it runs as it is"):
        assert graphed(step, True) is step
    on_a_gpu = dataclasses.replace(step, device=torch.device("cuda"))  # (nothing moved: only asked)
    assert not_replayable(on_a_gpu) is None
    assert "per-image modules" in not_replayable(dataclasses.replace(on_a_gpu, modules=(object(),)))
    adc = make_strategy(config_of(data=scene.root, strategy="adc"), plan, scene.radius, torch.Generator())
    assert "ADC" in not_replayable(dataclasses.replace(on_a_gpu, strategy=adc))


def test_on_a_gpu_the_captured_graph_trains_as_the_step_does(mini_demo, device):
    """The graph itself (pytest --device cuda): captured with Warp's launches and sorts in it, replayed without a
    wait for the GPU (torch's sync debug mode), training as the step run as it is does (to the GPU's atomics)."""
    if device.type != "cuda":
        pytest.skip("a CUDA graph needs a GPU: pytest --device cuda")
    pair_room.forget_rooms()
    scene = load_scene(mini_demo, downscale=4)
    alone, plan = mcmc_step(scene, device, steps=30)  # the rates fall 100 times over the 30 steps: stale ones show
    graphed = GraphedStep(mcmc_step(scene, device, steps=30)[0])
    rate = graphed.step.optimizers["means"].param_groups[0]["lr"]
    for step in range(24):
        view_index = step % 3
        expected = alone(step, scene.train[view_index], plan, view_index)
        torch.cuda.set_sync_debug_mode("error" if graphed.captures else "default")
        try:
            got = graphed(step, scene.train[view_index], plan, view_index)
        finally:
            torch.cuda.set_sync_debug_mode("default")
        assert got.loss == pytest.approx(expected.loss, rel=1e-3), step
    assert graphed.captures >= 1 and graphed.replays >= 15
    assert graphed.step.optimizers["means"].param_groups[0]["lr"] is rate and float(rate) < 2e-5 * scene.radius
    (room,) = pair_room._rooms.values()
    assert len(room._ratios) >= graphed.replays and room.overflows == 0  # it followed the replays' counts
    for key in PARAM_KEYS:
        torch.testing.assert_close(graphed.step.model.params[key], alone.model.params[key], rtol=1e-3, atol=1e-4)
    graphed.check_finite()
