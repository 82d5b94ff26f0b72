"""--pose-opt (pose_refinement.py): the view matrix's gradient from the projection kernel's hand-written backward
against autograd through the torch projection and the dense reference renderer in float64; the corrections; and on
the cup with its training poses knocked off by about a degree, the PSNR the corrections win back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mcsplat.camera import Camera
from mcsplat.config import TrainConfig, config_of
from mcsplat.pose_refinement import PoseRefinement, correction_matrix
from mcsplat.render import render, set_cpu_threads
from mcsplat.render.project.torch_autograd import project_gaussians, view_dependent_colors
from mcsplat.render.project.warp_kernel import project_and_shade
from mcsplat.render.reference import reference_render
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.train import train

from tests.support.helpers import perturbed_cup
from tests.render.test_render import PARAMS, make_camera, on, random_splats
from tests.render.test_warp_kernels import wide_scene


def tilted_camera(width: int, height: int, dtype=torch.float64) -> Camera:
    """make_camera's intrinsics, looking at the origin from an oblique pose (every entry of W matters)."""
    camera = make_camera(width=width, height=height)
    view = correction_matrix(torch.tensor([0.3, -0.4, 0.2, 0.1, -0.2, 0.15], dtype=torch.float64), 1.0)
    return Camera(K=camera.K, world_to_camera=(view @ camera.world_to_camera.double()).to(dtype), width=width,
                  height=height)


def with_view_grad(camera: Camera, device) -> Camera:
    return Camera(K=camera.K.to(device), world_to_camera=camera.world_to_camera.to(device).clone().requires_grad_(),
                  width=camera.width, height=camera.height)


@pytest.mark.parametrize("antialiased", [False, True])
def test_view_matrix_gradient_of_the_projection_kernel_matches_torch_in_float64(antialiased, device):
    splats = on(device, wide_scene(9000, 2))  # over 2 x 4096: the CPU splits the Gaussians into ranges
    camera = tilted_camera(70, 50)
    kernel_camera, torch_camera = with_view_grad(camera, device), with_view_grad(camera, device)
    set_cpu_threads(2)
    try:
        projection, colors = project_and_shade(*(getattr(splats, p) for p in PARAMS), kernel_camera, 3,
                                               antialiased=antialiased)
    finally:
        set_cpu_threads(None)
    expected = project_gaussians(*(getattr(splats, p) for p in PARAMS[:4]), torch_camera, antialiased=antialiased)
    expected_colors = view_dependent_colors(splats.means, splats.sh, torch_camera, 3)
    shown = (projection.radii > 0).to(torch.float64)
    g = torch.Generator().manual_seed(int(antialiased))
    names = ("means2d", "conics", "depths") + (("compensations",) if antialiased else ())
    weights = [torch.randn(t.shape, generator=g, dtype=torch.float64).to(device)
               for t in (colors, *(getattr(expected, k) for k in names))]
    for outs, view in (((colors, *(getattr(projection, k) for k in names)), kernel_camera),
                       ((expected_colors, *(getattr(expected, k) for k in names)), torch_camera)):
        # Culled Gaussians get no gradient in the kernel; their outputs are placeholders in both paths.
        sum((o * w * shown.reshape(-1, *([1] * (o.dim() - 1)))).sum() for o, w in zip(outs, weights)).backward()
    got, want = kernel_camera.world_to_camera.grad, torch_camera.world_to_camera.grad
    assert want[:3].abs().max() > 0 and not want[3].any()
    torch.testing.assert_close(got, want, atol=1e-9 * want.abs().max().item(), rtol=1e-9)


def test_view_matrix_gradient_of_a_render_matches_the_reference(device):
    splats = random_splats(40, 6, dtype=torch.float64)
    camera = tilted_camera(40, 32)
    fast_camera, reference_camera = with_view_grad(camera, device), with_view_grad(camera, device)
    fast = render(on(device, splats), fast_camera, (0.2, 0.4, 0.6))
    reference = reference_render(on(device, splats), reference_camera, (0.2, 0.4, 0.6))
    torch.testing.assert_close(fast.rgb, reference.rgb, atol=1e-10, rtol=0)
    assert fast.alpha.max() > 0.5
    weights = torch.randn(fast.rgb.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(device)
    (fast.rgb * weights).sum().backward()
    (reference.rgb * weights).sum().backward()
    want = reference_camera.world_to_camera.grad
    torch.testing.assert_close(fast_camera.world_to_camera.grad, want, atol=1e-9 * want.abs().max().item(), rtol=1e-7)


def test_projection_kernel_gradcheck_of_the_view_matrix_float64(device):
    splats = on(device, random_splats(12, 4, dtype=torch.float64))
    camera = tilted_camera(30, 24)

    def f(view):
        moved = Camera(K=camera.K.to(device), world_to_camera=view, width=camera.width, height=camera.height)
        projection, colors = project_and_shade(splats.means, splats.quats, splats.scales, splats.opacities,
                                               splats.sh, moved, 3, antialiased=True)
        return projection.means2d, projection.conics, projection.depths, colors, projection.compensations

    view = camera.world_to_camera.to(device).clone().requires_grad_()
    assert torch.autograd.gradcheck(f, (view,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_a_correction_is_a_rigid_motion_in_the_camera_axes():
    assert torch.equal(correction_matrix(torch.zeros(6), 2.0), torch.eye(4))
    turn = correction_matrix(torch.tensor([0.0, 0.0, math.pi / 2, 0.0, 0.0, 0.0]), 1.0)
    torch.testing.assert_close(turn[:3, :3] @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    shift = correction_matrix(torch.tensor([0.0, 0.0, 0.0, 0.1, 0.0, -0.2]), 5.0)
    torch.testing.assert_close(shift[:3, 3], torch.tensor([0.5, 0.0, -1.0]))
    poses = PoseRefinement(3, 2.0, torch.device("cpu"), lr=1e-3, weight_decay=0.0)
    camera = make_camera()
    moved = poses.camera(1, camera)
    assert torch.equal(moved.world_to_camera.detach(), camera.world_to_camera)
    moved.world_to_camera[0, 3].backward()
    assert poses.deltas.grad[1].abs().sum() > 0 and not poses.deltas.grad[[0, 2]].any()


# ------------------------------------------------------------------------------------------------ on a capture
def _config(data: Path, out: Path, **options) -> TrainConfig:
    return config_of(data=data, out=out, downscale=4, steps=1500, quiet=True, lpips_net="alex", save_every=0,
                       save_renders=False, mcmc=MCMCConfig(cap_max=10_000), **options)


def test_pose_refinement_wins_back_what_perturbed_training_poses_cost(shared_data, tmp_path):
    from mcsplat.data import load_scene

    original = load_scene(shared_data / "colmap_cup", downscale=4)
    root = tmp_path / "cup"
    moved = perturbed_cup(shared_data, root, {v.name for v in original.train}, 1.0, 0.01, original.radius)
    exact = train(_config(shared_data / "colmap_cup", tmp_path / "exact"))["psnr"]
    plain = train(_config(root, tmp_path / "plain"))["psnr"]
    refined = train(_config(root, tmp_path / "refined", pose_opt=True))["psnr"]
    print(f"test PSNR {exact:.2f} dB with the exact poses, {plain:.2f} perturbed, {refined:.2f} perturbed with "
          f"--pose-opt")
    assert exact > plain + 1.0, "a degree off should cost the scene sharpness"
    assert refined - plain > 0.5 * (exact - plain), "most of the loss should come back"
    # The learned rotations undo the perturbation: each points against the rotation the pose was moved by.
    deltas = torch.load(tmp_path / "refined" / "checkpoint.pt", weights_only=True)["poses"]["deltas"]
    names = [view.name for view in load_scene(root, downscale=4).train]
    cosines = [float(np.dot(deltas[i, :3].numpy(), -moved[name]) / (np.linalg.norm(deltas[i, :3].numpy())
                                                                     * np.linalg.norm(moved[name])))
               for i, name in enumerate(names)]
    print(f"cosine of learned and undoing rotations: median {np.median(cosines):.2f}")
    assert np.median(cosines) > 0.5


def test_a_resumed_run_with_pose_opt_takes_the_same_steps(mini_demo, tmp_path):
    from mcsplat.errors import MCSplatError
    from mcsplat.run.events import Control, StepDone

    def config(out: Path, **options) -> TrainConfig:
        return config_of(data=mini_demo, out=out, steps=40, pose_opt=True, quiet=True, lpips_net="alex",
                           save_every=0, save_renders=False, mcmc=MCMCConfig(cap_max=3000), **options)

    train(config(tmp_path / "straight"))
    control = Control()

    def stop_at_20(event) -> None:
        if isinstance(event, StepDone) and event.step == 20:
            control.stop()

    with pytest.raises(MCSplatError, match="stopped at step 20"):
        train(config(tmp_path / "stopped"), [stop_at_20], control)
    train(config(tmp_path / "stopped", resume=True))
    straight = torch.load(tmp_path / "straight" / "checkpoint.pt", weights_only=True)
    resumed = torch.load(tmp_path / "stopped" / "checkpoint.pt", weights_only=True)
    assert straight["poses"]["deltas"].abs().max() > 0
    assert torch.equal(straight["poses"]["deltas"], resumed["poses"]["deltas"])
    for key, value in straight["model"].items():
        assert torch.equal(value, resumed["model"][key]), key
