"""The normal map (render(outputs={"normals"}), render/outputs/normals.py) against the dense reference renderer: each
Gaussian's normal found another way (the covariance's smallest eigenvector) and composited by the reference, forward and
every gradient, in float64 and float32, through each compositing kernel."""

from __future__ import annotations

import math

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.geometry.depth_normals import normals_from_depth, points_from_depth
from mcsplat.render import Splats, render
from mcsplat.render.composite.function import cpu_kernels, set_cpu_kernels
from mcsplat.render.reference import reference_composite, reference_normals, reference_project

from tests.render.test_render import assert_close_relative, leaf, make_camera, random_splats

GRADIENT_PARAMS = ("means", "quats", "scales", "opacities")


def reference_normal_map(splats: Splats, camera: Camera) -> torch.Tensor:
    means2d, conics, depths, radii, tile_min, tile_max, _ = reference_project(
        splats.means, splats.quats, splats.scales, splats.opacities, camera)
    normals = reference_normals(splats.means, splats.quats, splats.scales, camera)
    zero = torch.zeros(3, dtype=splats.means.dtype)
    return reference_composite(means2d, conics, splats.opacities, normals, depths, radii, tile_min, tile_max, zero,
                               camera.width, camera.height)[0]


def random_linear_loss(image: torch.Tensor, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (image * torch.randn(image.shape, generator=g, dtype=torch.float64).to(image.dtype)).sum()


def rendered_with(kernels: str, splats: Splats, camera: Camera, **outputs):
    """(the render through `kernels` of leaf copies of `splats`, those leaves, float64 leaves for the reference).
    The reference runs in float64 always: the eigenvector's backward divides by the gaps between the eigenvalues,
    which float32 rounding turns into noise of about 1e-3 of the scales' gradient."""
    fast_in = leaf(splats)
    ref_in = leaf(Splats(*(getattr(splats, p).double() for p in ("means", "quats", "scales", "opacities", "sh"))))
    previous = cpu_kernels()
    set_cpu_kernels(kernels)
    try:
        return render(fast_in, camera, **outputs), fast_in, ref_in
    finally:
        set_cpu_kernels(previous)


@pytest.mark.parametrize("kernels,dtype,rtol", [("simd", torch.float32, 2e-4), ("tile", torch.float32, 2e-4),
                                                ("scalar", torch.float64, 1e-8)])
@pytest.mark.parametrize("seed", [0, 1])
def test_normal_map_and_its_gradients_match_the_reference(kernels, dtype, rtol, seed):
    splats = random_splats(80, seed, dtype=dtype, log_scale=(-3.0, -1.2))
    camera = make_camera(45, 37)
    out, fast_in, ref_in = rendered_with(kernels, splats, camera, outputs={"normals"})
    fast = out.normal
    random_linear_loss(fast, seed).backward()
    expected = reference_normal_map(ref_in, camera)
    random_linear_loss(expected, seed).backward()
    assert fast.shape == (37, 45, 3) and expected.abs().max() > 0.5, "the scene should cover part of the image"
    torch.testing.assert_close(fast.double(), expected, atol=1e-5 if dtype == torch.float32 else 1e-10, rtol=0)
    for name in GRADIENT_PARAMS:
        assert_close_relative(getattr(fast_in, name).grad.double(), getattr(ref_in, name).grad, rtol, name)


def flat_disk(tilt_degrees: float, dtype=torch.float64, radius: float = 0.5) -> Splats:
    """One opaque Gaussian flattened along its local z, rotated about the x axis, in front of make_camera()."""
    half = math.radians(tilt_degrees) / 2
    quat = torch.tensor([[math.cos(half), math.sin(half), 0.0, 0.0]], dtype=dtype)
    return Splats(means=torch.zeros(1, 3, dtype=dtype), quats=quat,
                  scales=torch.tensor([[radius, radius, 0.01]], dtype=dtype),
                  opacities=torch.tensor([0.99], dtype=dtype), sh=torch.zeros(1, 1, 3, dtype=dtype))


@pytest.mark.parametrize("tilt", [0.0, 30.0, 150.0])
def test_a_flat_disk_shows_its_normal_facing_the_camera(tilt):
    """At the centre pixel the map is 0.99 times the disk's axis (its local z turned by `tilt` about x), flipped so
    that it points back at the camera (negative camera z): 150 degrees puts the axis away from the camera."""
    camera = Camera(K=intrinsics(50.0, 50.0, 22.5, 18.5), world_to_camera=make_camera().world_to_camera,
                    width=45, height=37)
    normal = render(flat_disk(tilt), camera, outputs={"normals"}).normal[18, 22]
    angle = math.radians(tilt)
    axis = torch.tensor([0.0, -math.sin(angle), math.cos(angle)], dtype=torch.float64)
    if axis[2] > 0:
        axis = -axis
    torch.testing.assert_close(normal, 0.99 * axis, atol=2e-3, rtol=0)


def test_a_render_without_normals_has_none_and_the_same_image():
    splats = random_splats(50, 3)
    camera = make_camera()
    plain, with_normals = render(splats, camera), render(splats, camera, outputs={"normals"})
    assert plain.normal is None
    assert torch.equal(plain.rgb, with_normals.rgb) and torch.equal(plain.alpha, with_normals.alpha)


def test_the_normals_are_the_shortest_axis_whatever_its_index():
    """The same disk with its thin axis stored as x, y or z (quaternion and scales permuted alike) has one normal."""
    base = flat_disk(20.0)
    found = []
    for thin in range(3):
        scales = torch.full((1, 3), 0.5, dtype=torch.float64)
        scales[0, thin] = 0.01
        # A rotation taking local axis `thin` to local z: about y for x, about x for y, none for z.
        turn = {0: [math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0],
                1: [math.cos(math.pi / 4), -math.sin(math.pi / 4), 0.0, 0.0], 2: [1.0, 0.0, 0.0, 0.0]}[thin]
        quat = _quaternion_product(base.quats[0], torch.tensor(turn, dtype=torch.float64))[None]
        disk = Splats(base.means, quat, scales, base.opacities, base.sh)
        found.append(render(disk, make_camera(45, 37), outputs={"normals"}).normal[18, 22])
    torch.testing.assert_close(found[0], found[2], atol=2e-3, rtol=0)
    torch.testing.assert_close(found[1], found[2], atol=2e-3, rtol=0)


def _quaternion_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def test_the_normal_of_a_planes_depth_map_is_the_planes_normal():
    """A tilted plane's exact depth at each pixel centre: every interior pixel gets the plane's normal (facing the
    camera) to rounding; the border and a hole (depth 0) get none."""
    camera = Camera(K=intrinsics(40.0, 44.0, 20.3, 15.1), world_to_camera=make_camera().world_to_camera,
                    width=40, height=30)
    normal = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, -1.0], dtype=torch.float64), dim=0)
    offset = float(normal @ torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))  # the plane through (0, 0, 3)
    rays = points_from_depth(torch.ones(30, 40, dtype=torch.float64), camera)
    depth = offset / (rays @ normal)
    depth[10, 12] = 0.0
    found, valid = normals_from_depth(depth, camera)
    assert not valid[0].any() and not valid[:, -1].any() and not valid[10, 12] and not valid[10, 13]
    assert valid.sum() == 28 * 38 - 5
    torch.testing.assert_close(found[valid], normal.expand(int(valid.sum()), 3), atol=1e-10, rtol=0)
    assert (found[~valid] == 0).all()


def test_the_median_depths_normal_agrees_with_the_normal_map_on_a_flat_disk():
    """A disk seen at 35 degrees: the normal of its median depth (where each ray crosses its plane) and its normal
    map point the same way inside it; the expected depth (each Gaussian at its centre's depth) would not."""
    camera = make_camera(45, 37, dtype=torch.float64)
    out = render(flat_disk(35.0, radius=1.0), camera, outputs={"median_depth", "normals"})
    from_depth, valid = normals_from_depth(out.median_depth, camera)
    inside = valid & (out.alpha > 0.5)
    assert inside.sum() > 100
    mapped = torch.nn.functional.normalize(out.normal[inside], dim=-1)
    assert (mapped * from_depth[inside]).sum(dim=-1).min() > 0.999
    flat, flat_valid = normals_from_depth(out.depth, camera)
    assert (torch.nn.functional.normalize(out.normal[flat_valid & inside], dim=-1)
            * flat[flat_valid & inside]).sum(dim=-1).max() < 0.95


def reference_planar_depth(splats: Splats, camera: Camera) -> torch.Tensor:
    """The planes' depth the reference way: composited normals and plane distances, each pixel's ray from K^-1."""
    means2d, conics, depths, radii, tile_min, tile_max, _ = reference_project(
        splats.means, splats.quats, splats.scales, splats.opacities, camera)
    normals = reference_normals(splats.means, splats.quats, splats.scales, camera)
    w2c = camera.world_to_camera.to(splats.means.dtype)
    distances = (normals * (splats.means @ w2c[:3, :3].T + w2c[:3, 3])).sum(dim=-1, keepdim=True)
    zero = torch.zeros(3, dtype=splats.means.dtype)
    composite = [reference_composite(means2d, conics, splats.opacities, values, depths, radii, tile_min, tile_max,
                                     zero, camera.width, camera.height)[0]
                 for values in (normals, distances.expand(-1, 3))]
    ys, xs = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                            torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    pixels = torch.stack([xs + 0.5, ys + 0.5, torch.ones_like(xs)], dim=-1)
    rays = pixels @ torch.linalg.inv(camera.K.double()).T.to(splats.means.dtype)
    slant = (composite[0] * rays).sum(dim=-1)
    depth = composite[1][..., 0] / torch.where(slant.abs() >= 1e-3, slant, torch.ones_like(slant))
    return torch.where((slant.abs() >= 1e-3) & (depth > 0), depth, torch.zeros_like(depth))


@pytest.mark.parametrize("kernels,dtype,rtol", [("simd", torch.float32, 2e-3), ("scalar", torch.float64, 1e-8)])
def test_the_planar_depth_and_its_gradients_match_the_reference(kernels, dtype, rtol):
    splats = random_splats(80, 5, dtype=dtype, log_scale=(-3.0, -1.2))
    camera = make_camera(45, 37)
    fast, fast_in, ref_in = rendered_with(kernels, splats, camera, outputs={"planar_depth"})
    expected = reference_planar_depth(ref_in, camera)
    # Pixels where a plane is seen almost edge-on are ill-conditioned; compare where it is well seen.
    seen = (expected > 0) & (fast.planar_depth.double() > 0) & (fast.alpha.double() > 0.3)
    assert fast.normal is None and seen.sum() > 100
    torch.testing.assert_close(fast.planar_depth.double()[seen], expected[seen], atol=2e-4, rtol=1e-3)
    weights = torch.randn(expected.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    (fast.planar_depth * torch.where(seen, weights, 0.0).to(dtype)).sum().backward()
    (expected * torch.where(seen, weights, 0.0)).sum().backward()
    for name in GRADIENT_PARAMS:
        assert_close_relative(getattr(fast_in, name).grad.double(), getattr(ref_in, name).grad, rtol, name)


def test_a_tilted_disks_planar_depth_is_its_plane_and_its_normal_the_disks():
    """Inside a disk seen at 35 degrees the planar depth is where each ray meets the disk's plane, and the normal of
    that depth map is the disk's normal, as the normal map says."""
    camera = make_camera(45, 37, dtype=torch.float64)
    out = render(flat_disk(35.0, radius=1.0), camera, outputs={"normals", "planar_depth"})
    angle = math.radians(35.0)
    axis = torch.tensor([0.0, math.sin(angle), -math.cos(angle)], dtype=torch.float64)  # facing the camera
    rays = points_from_depth(torch.ones(37, 45, dtype=torch.float64), camera)
    plane = (axis @ torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)) / (rays @ axis)
    inside = out.alpha > 0.5
    assert inside.sum() > 200
    torch.testing.assert_close(out.planar_depth[inside], plane[inside], atol=1e-9, rtol=0)
    from_depth, valid = normals_from_depth(out.planar_depth, camera)
    both = valid & inside
    torch.testing.assert_close(from_depth[both], axis.expand(int(both.sum()), 3), atol=1e-9, rtol=0)
