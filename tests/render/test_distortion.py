"""2DGS's depth distortion (render(outputs={"distortion"}), render/outputs/distortion.py) against the dense reference
renderer's sum over every ordered pair of a pixel's Gaussians, forward and every gradient, in float64 and float32,
through each compositing kernel; and its value where it is known by hand."""

from __future__ import annotations

import pytest
import torch

from mcsplat.camera import Camera
from mcsplat.render import Splats, render
from mcsplat.render.reference import reference_distortion, reference_project

from tests.render.test_render import assert_close_relative, make_camera, random_splats
from tests.render.test_normals import GRADIENT_PARAMS, random_linear_loss, rendered_with


def reference_distortion_map(splats: Splats, camera: Camera) -> torch.Tensor:
    means2d, conics, depths, radii, tile_min, tile_max, _ = reference_project(
        splats.means, splats.quats, splats.scales, splats.opacities, camera)
    w2c = camera.world_to_camera.to(splats.means.dtype)
    inverse = 1.0 / (splats.means @ w2c[2, :3] + w2c[2, 3])
    return reference_distortion(means2d, conics, splats.opacities, inverse, depths, radii, tile_min, tile_max,
                                camera.width, camera.height)


@pytest.mark.parametrize("kernels,dtype,atol,rtol", [("simd", torch.float32, 1e-6, 2e-4),
                                                     ("tile", torch.float32, 1e-6, 2e-4),
                                                     ("scalar", torch.float64, 1e-12, 1e-8)])
def test_the_distortion_and_its_gradients_match_the_pairwise_sum(kernels, dtype, atol, rtol):
    # Wide, overlapping Gaussians at depths 2-4 in front of the camera: many pixels composite several of them.
    splats = random_splats(60, 7, dtype=dtype, log_scale=(-2.5, -1.2))
    camera = make_camera(40, 32)
    out, fast_in, ref_in = rendered_with(kernels, splats, camera, outputs={"distortion"})
    expected = reference_distortion_map(ref_in, camera)
    assert out.normal is None and out.planar_depth is None
    assert expected.max() > 1e-3 and (expected > 1e-5).float().mean() > 0.3, "pixels should see several depths"
    torch.testing.assert_close(out.distortion.double(), expected, atol=atol, rtol=0)
    random_linear_loss(out.distortion, 3).backward()
    random_linear_loss(expected, 3).backward()
    for name in GRADIENT_PARAMS:
        assert_close_relative(getattr(fast_in, name).grad.double(), getattr(ref_in, name).grad, rtol, name)


def disk(depth: float, opacity: float, radius: float = 2.0) -> Splats:
    """A wide Gaussian, flat along z, on the camera's axis at camera depth `depth` (make_camera's camera is 3 units
    behind the origin)."""
    return Splats(means=torch.tensor([[0.0, 0.0, depth - 3.0]], dtype=torch.float64),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64),
                  scales=torch.tensor([[radius, radius, 0.01]], dtype=torch.float64),
                  opacities=torch.tensor([opacity], dtype=torch.float64), sh=torch.zeros(1, 1, 3, dtype=torch.float64))


def together(*parts: Splats) -> Splats:
    return Splats(*(torch.cat([getattr(p, name) for p in parts]) for name in
                    ("means", "quats", "scales", "opacities", "sh")))


def test_two_layers_give_their_weights_times_the_gap_squared_and_one_layer_none():
    """Near the centre of two wide disks at depths 2 and 5 (opacities 0.6 and 0.5) the weights are 0.6 and 0.4 x 0.5,
    so the distortion is 0.6 x 0.2 x (1/2 - 1/5)^2 = 0.0108; one disk alone, or both at one depth, give 0."""
    camera = make_camera(45, 37, dtype=torch.float64)
    centre = (17, 23)  # the principal point is at (23.8, 17.8): this pixel's centre is 0.3 pixel from it each way
    two = render(together(disk(2.0, 0.6), disk(5.0, 0.5)), camera, outputs={"distortion"}).distortion
    assert two[centre].item() == pytest.approx(0.6 * 0.4 * 0.5 * (1 / 2 - 1 / 5) ** 2, rel=1e-3)
    one = render(disk(2.0, 0.6), camera, outputs={"distortion"}).distortion
    same = render(together(disk(3.0, 0.6), disk(3.0, 0.5)), camera, outputs={"distortion"}).distortion
    assert one.abs().max() < 1e-12 and same.abs().max() < 1e-12


def test_a_render_without_the_distortion_has_none_and_the_same_image():
    splats = random_splats(50, 3)
    camera = make_camera()
    plain, with_it = render(splats, camera), render(splats, camera, outputs={"distortion"})
    assert plain.distortion is None and with_it.distortion is not None
    assert torch.equal(plain.rgb, with_it.rgb) and torch.equal(plain.alpha, with_it.alpha)


def test_gradient_descent_on_the_distortion_pulls_two_layers_together():
    """The term's gradient moves the layers toward each other (or fades one): after some steps of descent on the
    distortion alone it has fallen by most of its value."""
    camera = make_camera(45, 37, dtype=torch.float64)
    layers = together(disk(2.0, 0.6), disk(3.0, 0.5))
    means = layers.means.clone().requires_grad_()
    first = None
    for _ in range(60):
        value = render(Splats(means, layers.quats, layers.scales, layers.opacities, layers.sh), camera,
                       outputs={"distortion"}).distortion.sum()
        first = value.item() if first is None else first
        means.grad = None
        value.backward()
        with torch.no_grad():
            means -= 0.5 * means.grad
    assert value.item() < 0.2 * first
    assert (means[1, 2] - means[0, 2]).item() < 0.5, "the far layer should come forward, or the near one back"
