"""--antialiased: Mip-Splatting's 2D filter (opacity scaled by sqrt(det before / det after the 0.3 px low-pass)) in the
projection kernel, the torch projection and the dense reference renderer, and the flag's way from the run's
configuration to every render and to the .spz header."""

from __future__ import annotations

import gzip
import math
import struct

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.gaussians import GaussianModel
from mcsplat.render import Splats, render, set_cpu_threads
from mcsplat.render.project.torch_autograd import project_gaussians
from mcsplat.render.project.warp_kernel import project_and_shade

from tests.render.test_render import PARAMS, SEEDS, compare_with_reference, make_camera, on, random_splats
from tests.render.test_warp_kernels import wide_scene


@pytest.mark.parametrize("seed", SEEDS)
def test_antialiased_render_matches_reference(seed, device):
    # Scales from a tenth of a pixel to several pixels: the compensation ranges from ~0.03 to ~1.
    splats = random_splats(60, seed, log_scale=(-6.0, -1.5))
    fast, _ = compare_with_reference(splats, make_camera(), background=(0.2, 0.5, 0.9), seed=seed, device=device,
                                     antialiased=True)
    plain = render(on(device, splats), make_camera().to(device))
    assert (fast.alpha <= plain.alpha + 1e-6).all() and (fast.alpha < plain.alpha - 0.01).any(), \
        "the filter only ever lowers a splat's opacity"


def test_antialiased_with_opacity_aware_radius_matches_reference(device):
    compare_with_reference(random_splats(60, 5, log_scale=(-6.0, -1.5)), make_camera(), None, device=device,
                           antialiased=True, opacity_aware_radius=True)


def test_projection_kernel_compensation_matches_torch_in_float64(device):
    splats = on(device, wide_scene(9000, 3))
    camera = make_camera(width=70, height=50, distance=3.0).to(device)
    kernel_in = [getattr(splats, p).clone().requires_grad_() for p in PARAMS]
    torch_in = [getattr(splats, p).clone().requires_grad_() for p in PARAMS]
    set_cpu_threads(2, split_small_work=True)
    try:
        projection, _ = project_and_shade(*kernel_in, camera, 3, antialiased=True)
    finally:
        set_cpu_threads(None)
    expected = project_gaussians(*torch_in[:4], camera, antialiased=True)
    shown = projection.radii > 0
    torch.testing.assert_close(projection.compensations[shown], expected.compensations[shown], atol=1e-12, rtol=1e-12)
    assert projection.compensations[shown].min() < 0.2 and projection.compensations[shown].max() > 0.9
    weights = torch.randn(projection.compensations.shape, generator=torch.Generator().manual_seed(0),
                          dtype=torch.float64).to(device) * shown
    (projection.compensations * weights).sum().backward()
    (expected.compensations * weights).sum().backward()
    for name, a, b in zip(PARAMS, kernel_in, torch_in):
        if name in ("means", "quats", "scales"):
            assert b.grad.abs().max() > 0, name
            torch.testing.assert_close(a.grad, b.grad, atol=1e-10 * b.grad.abs().max().item(), rtol=1e-9, msg=name)


def test_projection_kernel_gradcheck_of_the_compensation_float64(device):
    splats = on(device, random_splats(12, 4, dtype=torch.float64, log_scale=(-5.0, -2.0)))
    camera = make_camera(width=30, height=24).to(device)
    inputs = tuple(getattr(splats, p).clone().requires_grad_() for p in ("means", "quats", "scales"))

    def f(means, quats, scales):
        projection, _ = project_and_shade(means, quats, scales, splats.opacities, splats.sh, camera, 3,
                                          antialiased=True)
        return projection.compensations, projection.conics

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


def single_splat(sigma_px: float, distance: float = 3.0, focal: float = 50.0, opacity: float = 0.9) -> Splats:
    """One isotropic Gaussian on the optical axis whose projection has standard deviation `sigma_px` pixels."""
    scale = sigma_px * distance / focal
    return Splats(means=torch.zeros(1, 3, dtype=torch.float64), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]],
                  dtype=torch.float64), scales=torch.full((1, 3), scale, dtype=torch.float64),
                  opacities=torch.tensor([opacity], dtype=torch.float64), sh=torch.zeros(1, 1, 3, dtype=torch.float64))


@pytest.mark.parametrize("sigma_px", [0.2, 0.5, 1.0, 3.0])
def test_a_splat_covers_its_own_area_with_the_filter(sigma_px):
    # The integral of o exp(-x^T S^-1 x / 2) over the image is o 2 pi sqrt(det S). The 0.3 px low-pass grows S by
    # 0.3 I; the filter's factor sqrt(det S / det(S + 0.3 I)) gives the area back, so a splat's total alpha is that
    # of the Gaussian itself however small it is. Without it a splat of a fifth of a pixel covers 8x its area.
    camera = Camera(K=intrinsics(50.0, 50.0, 32.0, 32.0), world_to_camera=make_camera().world_to_camera.double(),
                    width=64, height=64)
    splat = single_splat(sigma_px)
    blurred = sigma_px ** 2 + 0.3
    ys, xs = torch.meshgrid(*(torch.arange(64, dtype=torch.float64) + 0.5,) * 2, indexing="ij")
    gaussian = torch.exp(-((xs - 32.0) ** 2 + (ys - 32.0) ** 2) / (2.0 * blurred))

    def expected(peak: float) -> torch.Tensor:  # pixel centres, alphas under 1/255 skipped
        alpha = peak * gaussian
        return torch.where(alpha >= 1.0 / 255.0, alpha, 0.0)

    filtered = render(splat, camera, antialiased=True).alpha
    plain = render(splat, camera).alpha
    torch.testing.assert_close(filtered, expected(0.9 * sigma_px ** 2 / blurred), atol=1e-12, rtol=1e-9)
    torch.testing.assert_close(plain, expected(0.9), atol=1e-12, rtol=1e-9)
    true_area = 0.9 * 2.0 * math.pi * sigma_px ** 2
    assert float(filtered.sum()) == pytest.approx(true_area, rel=0.11)
    if sigma_px < 0.3:
        assert float(plain.sum()) > 7.0 * true_area


def test_the_filter_keeps_a_zoomed_out_render_close_to_the_downsampled_one():
    # Fine detail (splats under a pixel once zoomed out 4x) rendered at 40x40 against the 160x160 render averaged
    # over 4x4 blocks: without the filter each splat paints at least the low-pass's 0.3 px^2 and the small image
    # comes out too opaque; with it, much closer to what the pixels should average to.
    splats = random_splats(400, 3, log_scale=(-5.5, -4.0), opacity=(0.3, 0.9), sh_bases=1)
    splats.means[:, 2] *= 0.1

    def camera(size: int) -> Camera:
        f = 60.0 * size / 40
        return Camera(K=intrinsics(f, f, size / 2, size / 2), world_to_camera=make_camera().world_to_camera,
                      width=size, height=size)

    errors = {}
    for antialiased in (False, True):
        splats.antialiased = antialiased
        big = render(splats, camera(160), background=(1.0, 1.0, 1.0)).rgb
        small = render(splats, camera(40), background=(1.0, 1.0, 1.0)).rgb
        downsampled = torch.nn.functional.avg_pool2d(big.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
        errors[antialiased] = float((small - downsampled).abs().mean())
    assert errors[True] < 0.2 * errors[False], errors


def test_a_model_carries_the_flag_to_render_and_subsets():
    model = GaussianModel.from_points(torch.randn(50, 3) * 0.3, torch.rand(50, 3), init_scale=0.3, init_opacity=0.5)
    camera = make_camera()
    plain = render(model, camera).alpha
    model.antialiased = True
    assert torch.equal(render(model, camera).alpha, render(model, camera, antialiased=True).alpha)
    assert not torch.equal(render(model, camera).alpha, plain)
    assert model.subset(torch.arange(10)).antialiased


def test_train_with_antialiased_sets_the_flag_everywhere(tmp_path, mini_demo, capsys):
    from mcsplat.cli import main
    from mcsplat.run.trained import load

    out = tmp_path / "run"
    assert main(["train", str(mini_demo), "--out", str(out), "--steps", "30", "--antialiased", "--quiet",
                 "--lpips-net", "alex", "--no-save-renders"]) == 0
    run = load(out, torch.device("cpu"))
    assert run.config.antialiased and run.model.antialiased
    assert main(["export", str(out), "--out", str(tmp_path / "scene.spz")]) == 0
    header = gzip.decompress((tmp_path / "scene.spz").read_bytes())[:16]
    assert struct.unpack("<IIIBBBB", header)[5] == 1, "the .spz flags byte says antialiased"
    assert main(["export", str(out), "--out", str(tmp_path / "scene.splat")]) == 0
    assert "cannot record" in capsys.readouterr().out
