"""The Warp rasterizer against the dense pure-PyTorch oracle (mcsplat.render.reference)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.render import Splats, render, set_cpu_threads
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.composite.function import CompositeFunction, composite, cpu_kernels, set_cpu_kernels
from mcsplat.render.project.torch_autograd import project_gaussians
from mcsplat.render.reference import reference_composite, reference_render

from tests.support.helpers import median_gaussian_case

SEEDS = [0, 1, 2, 3]
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def make_camera(width=45, height=37, distance=3.0, dtype=torch.float32) -> Camera:
    w2c = torch.eye(4)
    w2c[2, 3] = distance
    return Camera(K=intrinsics(50.0, 52.0, width / 2 + 1.3, height / 2 - 0.7), world_to_camera=w2c,
                  width=width, height=height)


def random_splats(n, seed, dtype=torch.float32, spread=1.0, log_scale=(-3.5, -1.5), opacity=(0.01, 0.99),
                  sh_bases=16) -> Splats:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2.0 * spread
    lo, hi = log_scale
    scales = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=dtype))
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g, dtype=dtype)
    return Splats(means=means, quats=torch.randn(n, 4, generator=g, dtype=dtype), scales=scales,
                  opacities=opacities, sh=torch.randn(n, sh_bases, 3, generator=g, dtype=dtype) * 0.3)


def on(device, splats: Splats) -> Splats:
    return Splats(*(getattr(splats, p).to(device) for p in PARAMS))


def leaf(splats: Splats, device="cpu") -> Splats:
    return Splats(*(getattr(splats, p).detach().to(device).clone().requires_grad_() for p in PARAMS))


def gradients(result, splats: Splats, seed: int):
    """Backward of a random linear function of rgb, alpha and depth; returns the parameter and means2d gradients."""
    g = torch.Generator().manual_seed(1000 + seed)
    h, w = result.alpha.shape
    dtype, device = result.rgb.dtype, result.rgb.device
    loss = ((result.rgb * torch.randn(h, w, 3, generator=g, dtype=dtype).to(device)).sum()
            + (result.alpha * torch.randn(h, w, generator=g, dtype=dtype).to(device)).sum()
            + (result.depth * torch.randn(h, w, generator=g, dtype=dtype).to(device)).sum())
    for p in PARAMS:
        getattr(splats, p).grad = None
    loss.backward()
    grads = {p: getattr(splats, p).grad.clone() for p in PARAMS}
    grads["means2d"] = result.means2d.grad.clone()
    return grads


def assert_close_relative(actual, expected, rtol, name):
    scale = expected.abs().max().clamp(min=1e-12)
    error = (actual - expected).abs().max() / scale
    assert error <= rtol, f"{name}: max error {error:.2e} of the largest magnitude (allowed {rtol:.0e})"


def compare_with_reference(splats, camera, background, rtol=1e-4, seed=0, device="cpu", **options):
    """Render on `device` with the Warp rasterizer and with the dense oracle: images and gradients must agree."""
    fast_in, ref_in = leaf(splats, device), leaf(splats, device)
    camera = camera.to(device)
    fast = render(fast_in, camera, background, **options)
    ref = reference_render(ref_in, camera, background, **options)
    assert torch.equal(fast.radii, ref.radii)
    torch.testing.assert_close(fast.rgb, ref.rgb, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.alpha, ref.alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(fast.depth, ref.depth, atol=1e-4, rtol=1e-5)
    if fast.alpha.sum() == 0:
        return fast, ref
    fast_grads, ref_grads = gradients(fast, fast_in, seed), gradients(ref, ref_in, seed)
    for name in ref_grads:
        assert_close_relative(fast_grads[name], ref_grads[name], rtol, name)
    return fast, ref


@pytest.mark.parametrize("seed", SEEDS)
def test_random_scene_matches_reference(seed, device):
    splats = random_splats(60, seed)
    fast, _ = compare_with_reference(splats, make_camera(), background=(0.2, 0.5, 0.9), seed=seed, device=device)
    assert fast.alpha.max() > 0.5, "the scene should cover part of the image"


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_early_termination_and_alpha_clamp_match_reference(seed, device):
    # A stack of large, nearly opaque Gaussians on the optical axis: alpha is clamped at 0.99 and the walk stops
    # once the transmittance would fall below 1e-4, while random splats lie in front and behind.
    stack = Splats(means=torch.tensor([[0.0, 0.0, z] for z in (-0.4, -0.2, 0.0, 0.2, 0.4)]),
                   quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(5, 1), scales=torch.full((5, 3), 0.25),
                   opacities=torch.full((5,), 0.999), sh=torch.randn(5, 16, 3, generator=torch.Generator().manual_seed(seed)))
    extra = random_splats(40, seed)
    splats = Splats(*(torch.cat([getattr(stack, p), getattr(extra, p)]) for p in PARAMS))
    camera = make_camera()
    fast, _ = compare_with_reference(splats, camera, background=(1.0, 1.0, 1.0), seed=seed, device=device)
    transmittance = 1.0 - fast.alpha.detach().double()
    # Five clamped alphas would leave T = 1e-10; the walk stops before T falls under 1e-4, so T bottoms out there.
    assert transmittance.min() >= 1e-4 - 1e-6
    assert transmittance.min() < 1e-3, "some pixel must see several clamped alphas and reach the stopping point"


def test_sh_degrees_and_background(device):
    splats = random_splats(50, 7)
    for degree in range(4):
        compare_with_reference(splats, make_camera(), background=(0.0, 1.0, 0.3), sh_degree=degree, device=device)


def test_opacity_aware_radius_matches_reference(device):
    fast, _ = compare_with_reference(random_splats(60, 11), make_camera(), None, opacity_aware_radius=True,
                                     device=device)
    plain = render(on(device, random_splats(60, 11)), make_camera().to(device))
    assert (fast.radii <= plain.radii).all() and (fast.radii < plain.radii).any()


@pytest.mark.parametrize("size", [(16, 16), (33, 70), (70, 33), (17, 1)])
def test_odd_and_non_square_images(size, device):
    width, height = size
    camera = Camera(K=intrinsics(40.0, 40.0, width / 2, height / 2), world_to_camera=make_camera().world_to_camera,
                    width=width, height=height)
    fast, _ = compare_with_reference(random_splats(50, 3), camera, background=(0.1, 0.2, 0.3), device=device)
    assert fast.rgb.shape == (height, width, 3)


def test_huge_gaussian_covering_the_whole_image(device):
    splats = Splats(means=torch.tensor([[0.05, -0.03, 0.0]]), quats=torch.tensor([[0.9, 0.1, 0.2, 0.3]]),
                    scales=torch.tensor([[3.0, 2.0, 2.5]]), opacities=torch.tensor([0.7]),
                    sh=torch.rand(1, 16, 3) * 0.2)
    camera = make_camera()
    fast, _ = compare_with_reference(splats, camera, background=(0.0, 0.0, 1.0), device=device)
    assert (fast.alpha > 0.4).all(), "a Gaussian much larger than the view covers every pixel"


def test_gaussians_behind_the_camera_are_culled(device):
    splats = random_splats(40, 5)
    behind = random_splats(10, 6)
    behind.means[:, 2] = -3.5 - behind.means[:, 2].abs()  # camera at z = -3 looking along +z
    mixed = Splats(*(torch.cat([getattr(splats, p), getattr(behind, p)]) for p in PARAMS))
    fast, _ = compare_with_reference(mixed, make_camera(), None, device=device)
    assert (fast.radii[40:] == 0).all() and not fast.contributed[40:].any()
    inputs = leaf(mixed, device)
    out = render(inputs, make_camera().to(device))
    out.rgb.sum().backward()
    assert (inputs.means.grad[40:] == 0).all() and torch.isfinite(inputs.means.grad).all()


def test_zero_gaussians_render_the_background():
    empty = leaf(Splats(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 1, 3)))
    out = render(empty, make_camera(), background=(0.25, 0.5, 0.75))
    assert torch.equal(out.rgb, torch.tensor([0.25, 0.5, 0.75]).expand(37, 45, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all() and out.num_pairs == 0
    out.rgb.sum().backward()
    assert empty.means.grad.shape == (0, 3)


def test_all_culled_renders_the_background_with_zero_gradients(device):
    splats = leaf(random_splats(20, 9), device)
    with torch.no_grad():
        splats.means[:, 2] -= 10.0  # everything behind the camera
    out = render(splats, make_camera().to(device), background=(1.0, 1.0, 1.0))
    assert (out.radii == 0).all() and (out.rgb == 1.0).all() and (out.alpha == 0).all()
    out.rgb.sum().backward()
    for p in PARAMS:
        assert (getattr(splats, p).grad == 0).all()


def test_depth_is_the_expected_camera_depth(device):
    # One opaque Gaussian facing the camera at known depth: expected depth there is exactly its z.
    splats = Splats(means=torch.tensor([[0.0, 0.0, 1.0]]), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
                    scales=torch.tensor([[0.3, 0.3, 0.01]]), opacities=torch.tensor([0.9]), sh=torch.zeros(1, 1, 3))
    out = render(on(device, splats), make_camera().to(device))
    assert float(out.depth[18, 22]) == pytest.approx(4.0, abs=1e-5)
    assert out.rgb[18, 22].tolist() == pytest.approx([0.5 * float(out.alpha[18, 22])] * 3, abs=1e-6)
    assert out.contributed.tolist() == [True]


def stacked_on_axis(depths, opacities, scale=0.6) -> Splats:
    """Large round Gaussians on the optical axis of make_camera() (the camera sits at z = -3)."""
    n = len(depths)
    return Splats(means=torch.tensor([[0.0, 0.0, z - 3.0] for z in depths]),
                  quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1), scales=torch.full((n, 3), scale),
                  opacities=torch.tensor(opacities), sh=torch.zeros(n, 1, 3))


KERNELS = [("simd", torch.float32), ("scalar", torch.float32), ("scalar", torch.float64)]


@pytest.mark.parametrize("kernels, dtype", KERNELS, ids=["simd", "scalar", "scalar-float64"])
@pytest.mark.parametrize("scene", ["random", "opaque stack"])
def test_median_depth_matches_reference(kernels, dtype, scene, device):
    """Each compositing kernel (the scalar one is the CUDA path) against the dense oracle's median depth."""
    splats = random_splats(60, 3, dtype=dtype)
    if scene == "opaque stack":  # clamped alphas and the early stop, in front of and behind random splats
        stack = stacked_on_axis([2.6, 2.8, 3.0, 3.2, 3.4], [0.999] * 5, scale=0.25)
        splats = Splats(*(torch.cat([getattr(stack, p).to(dtype), getattr(splats, p)[:, :1] if p == "sh"
                                     else getattr(splats, p)]) for p in PARAMS))
    previous = cpu_kernels()
    set_cpu_kernels(kernels)
    try:
        fast = render(on(device, splats), make_camera().to(device), outputs={"median_depth"})
    finally:
        set_cpu_kernels(previous)
    ref = reference_render(on(device, splats), make_camera().to(device))
    assert fast.median_depth.dtype == dtype and fast.median_depth.shape == fast.alpha.shape
    torch.testing.assert_close(fast.median_depth, ref.median_depth, atol=1e-4, rtol=1e-5)
    covered = ref.alpha.detach() > 0.5
    assert covered.float().mean() > 0.1 and (ref.median_depth[covered] > 0).all()
    assert (ref.median_depth[ref.alpha.detach() == 0] == 0).all()


@pytest.mark.parametrize("kernels, dtype", KERNELS, ids=["simd", "scalar", "scalar-float64"])
@pytest.mark.parametrize("seed", SEEDS[:2])
def test_median_gaussian_of_each_kernel_is_the_references(kernels, dtype, seed, device):
    """The kernels' own output, on the same projected inputs: which Gaussian each pixel's median is."""
    splats = on(device, random_splats(120, seed, dtype=dtype, log_scale=(-3.0, -1.5)))
    camera = make_camera(width=50, height=40).to(device)
    inputs, expected = median_gaussian_case(splats, camera)
    outputs = composite(*inputs, cpu_kernels=kernels, median_gaussian=True)
    assert outputs[4].dtype == torch.int32 and torch.equal(outputs[4].long(), expected)
    assert (expected >= 0).float().mean() > 0.3 and expected.unique().numel() > 10


def test_the_outputs_given_on_request_are_registered_passes(device):
    """render(outputs=...) runs the passes of what it names (outputs/passes.py) and no other; a name no pass gives is
    refused, naming those there are."""
    from mcsplat.render.outputs.passes import OUTPUTS, passes_for

    assert OUTPUTS == {"median_depth", "normals", "planar_depth", "distortion"}
    assert [sorted(p.gives) for p in passes_for({"planar_depth"})] == [["normals", "planar_depth"]]
    splats = on(device, stacked_on_axis([1.0, 1.5, 2.0], [0.3, 0.4, 0.9]))
    out = render(splats, make_camera().to(device), outputs={"planar_depth"})
    assert out.planar_depth is not None and out.normal is None and out.median_depth is None and out.distortion is None
    with pytest.raises(ValueError, match="no output depth_of_field; the outputs given on request are distortion, "
                                         "median_depth, normals, planar_depth"):
        render(splats, make_camera().to(device), outputs={"depth_of_field"})


def test_median_depth_is_where_the_accumulated_alpha_reaches_one_half(device):
    # On the axis, alpha is each Gaussian's opacity: 0.3, then 0.4 brings the accumulated alpha to 0.58 >= 0.5.
    out = render(on(device, stacked_on_axis([1.0, 1.5, 2.0], [0.3, 0.4, 0.9])), make_camera().to(device),
                 outputs={"median_depth"})
    centre = (18, 23)
    assert float(out.median_depth[centre]) == pytest.approx(1.5, abs=1e-3)
    # The expected depth lies between the layers: (0.3 * 1 + 0.7 * 0.4 * 1.5 + 0.42 * 0.9 * 2) / 0.958.
    assert float(out.depth[centre]) == pytest.approx(1.476 / 0.958, abs=5e-3)
    # Never reaching one half, the median is the last Gaussian composited.
    faint = render(on(device, stacked_on_axis([1.0, 1.5], [0.2, 0.2])), make_camera().to(device),
                   outputs={"median_depth"})
    assert float(faint.median_depth[centre]) == pytest.approx(1.5, abs=1e-3)


def test_median_depth_is_where_the_ray_crosses_a_flat_gaussian(device):
    """A tilted flat Gaussian: each pixel's median depth is the depth of its ray's crossing with the Gaussian's plane,
    not the centre's depth."""
    normal = torch.tensor([0.0, 0.6, -0.8])  # facing the camera at z = -3, tilted about the x axis
    half_angle = torch.acos(-normal[2]) / 2  # rotation of +z onto the normal's opposite side, about the x axis
    quat = torch.tensor([[float(torch.cos(half_angle)), float(torch.sin(half_angle)), 0.0, 0.0]])
    splats = Splats(means=torch.tensor([[0.0, 0.0, 0.0]]), quats=quat, scales=torch.tensor([[0.5, 0.5, 1e-4]]),
                    opacities=torch.tensor([0.95]), sh=torch.zeros(1, 1, 3))
    camera = make_camera()
    out = render(on(device, splats), camera.to(device), outputs={"median_depth"})
    rows, columns = torch.nonzero(out.alpha.cpu() >= 0.5, as_tuple=True)
    assert rows.numel() > 200
    rays = torch.stack([(columns + 0.5 - camera.cx) / camera.fx, (rows + 0.5 - camera.cy) / camera.fy,
                        torch.ones(rows.shape)], dim=1)
    plane_normal = torch.tensor([0.0, -float(torch.sin(2 * half_angle)), float(torch.cos(2 * half_angle))])
    crossing = 3.0 * plane_normal[2] / (rays @ plane_normal)  # the plane through (0, 0, 3) in camera coordinates
    torch.testing.assert_close(out.median_depth.cpu()[rows, columns], crossing, atol=2e-3, rtol=0)
    assert (crossing - 3.0).abs().max() > 0.1, "the centre's depth would be off by this much"


@pytest.mark.parametrize("kernels", ["simd", "scalar"])
def test_asking_for_median_depth_changes_no_other_output_or_gradient(kernels, device):
    splats = random_splats(80, 12)
    previous = cpu_kernels()
    set_cpu_kernels(kernels)
    outputs = []
    try:
        for median in (False, True):
            inputs = leaf(splats, device)
            out = render(inputs, make_camera().to(device), (0.3, 0.2, 0.1), outputs={"median_depth"} if median else ())
            assert (out.median_depth is not None) == median
            grads = gradients(out, inputs, 5)
            outputs.append([out.rgb.detach(), out.alpha.detach(), out.depth.detach(), out.contributed,
                            *grads.values()])
    finally:
        set_cpu_kernels(previous)
    assert all(torch.equal(a, b) for a, b in zip(*outputs))


@pytest.mark.parametrize("seed", SEEDS)
def test_composite_gradients_of_2d_quantities(seed, device):
    """CompositeFunction alone, on random 2D inputs: gradients of means2d, conics, opacities, colours, depths."""
    g = torch.Generator().manual_seed(seed)
    n, width, height = 80, 40, 35
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([width, height])
    # A random SPD 2D covariance per Gaussian, then its conic.
    axes = torch.randn(n, 2, 2, generator=g) * 4.0
    cov = axes @ axes.transpose(1, 2) + 2.0 * torch.eye(2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], dim=-1)
    opacities = torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    depths = torch.rand(n, generator=g) * 5 + 1
    radii = torch.ceil(3 * torch.linalg.eigvalsh(cov)[:, -1].sqrt()).to(torch.int32)
    tile_min = torch.clamp(torch.floor((means2d - radii[:, None]) / 16), min=0).to(torch.int32)
    tile_max = torch.minimum(torch.floor((means2d + radii[:, None]) / 16) + 1,
                             torch.tensor([3, 3])).to(torch.int32)
    background = torch.tensor([0.3, 0.6, 0.1])
    means2d, conics, opacities, colors, depths, radii, tile_min, tile_max, background = (
        t.to(device) for t in (means2d, conics, opacities, colors, depths, radii, tile_min, tile_max, background))
    bins = bin_gaussians(tile_min, tile_max, depths, radii, 3, 3)
    inputs = [t.clone().requires_grad_() for t in (means2d, conics, opacities, colors, depths)]
    ref_inputs = [t.clone().requires_grad_() for t in (means2d, conics, opacities, colors, depths)]
    rgb, alpha, depth, _ = CompositeFunction.apply(*inputs, background, bins, width, height)
    ref_rgb, ref_alpha, ref_depth = reference_composite(*ref_inputs[:2], ref_inputs[2], ref_inputs[3], ref_inputs[4],
                                                        radii, tile_min, tile_max, background, width, height)
    torch.testing.assert_close(rgb, ref_rgb, atol=1e-5, rtol=0)
    torch.testing.assert_close(alpha, ref_alpha, atol=1e-5, rtol=0)
    torch.testing.assert_close(depth, ref_depth, atol=1e-4, rtol=0)
    weights = [torch.randn(t.shape, generator=g).to(device) for t in (rgb, alpha, depth)]
    sum(((o * w).sum() for o, w in zip((rgb, alpha, depth), weights))).backward()
    sum(((o * w).sum() for o, w in zip((ref_rgb, ref_alpha, ref_depth), weights))).backward()
    for name, a, b in zip(("means2d", "conics", "opacities", "colors", "depths"), inputs, ref_inputs):
        assert_close_relative(a.grad, b.grad, 1e-4, name)


def test_gradcheck_float64_full_render(device):
    splats = leaf(random_splats(6, 21, dtype=torch.float64, log_scale=(-1.8, -1.2), opacity=(0.3, 0.8), sh_bases=4),
                  device)
    camera = make_camera(width=20, height=18).to(device)

    def f(means, quats, scales, opacities, sh):
        out = render(Splats(means, quats, scales, opacities, sh), camera, background=(0.1, 0.2, 0.3))
        return out.rgb, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, tuple(getattr(splats, p) for p in PARAMS), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_float64_composite(device):
    g = torch.Generator().manual_seed(4)
    n = 12
    means2d = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 20).requires_grad_()
    conics = torch.tensor([[0.05, 0.01, 0.04]], dtype=torch.float64).repeat(n, 1).requires_grad_()
    opacities = (torch.rand(n, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64).requires_grad_()
    depths = (torch.rand(n, generator=g, dtype=torch.float64) + 1).requires_grad_()
    radii = torch.full((n,), 30, dtype=torch.int32)
    tile_min = torch.zeros(n, 2, dtype=torch.int32)
    tile_max = torch.full((n, 2), 2, dtype=torch.int32)
    means2d, conics, opacities, colors, depths, radii, tile_min, tile_max = (
        t.detach().to(device).requires_grad_(t.requires_grad)
        for t in (means2d, conics, opacities, colors, depths, radii, tile_min, tile_max))
    bins = bin_gaussians(tile_min, tile_max, depths, radii, 2, 2)
    background = torch.tensor([0.5, 0.1, 0.9], dtype=torch.float64, device=device)

    def f(*inputs):
        return CompositeFunction.apply(*inputs, background, bins, 20, 20)[:3]

    assert torch.autograd.gradcheck(f, (means2d, conics, opacities, colors, depths), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_threaded_cpu_launcher_matches_single_thread():
    splats = random_splats(300, 13, log_scale=(-3.0, -2.0))
    camera = make_camera(width=96, height=80, distance=2.5)
    results = []
    try:
        for threads in (1, 2):
            set_cpu_threads(threads, split_small_work=True)
            inputs = leaf(splats)
            out = render(inputs, camera, background=(0.3, 0.3, 0.3))
            (out.rgb * torch.linspace(0, 1, 3)).sum().backward()
            results.append((out.rgb.detach(), {p: getattr(inputs, p).grad for p in PARAMS}))
    finally:
        set_cpu_threads(None)
    assert torch.equal(results[0][0], results[1][0]), "the forward must not depend on the thread count"
    for p in PARAMS:
        assert_close_relative(results[1][1][p], results[0][1][p], 1e-5, p)


def test_contributed_and_visibility_flags(device):
    splats = on(device, random_splats(60, 17))
    out = render(splats, make_camera().to(device))
    assert out.contributed.dtype == torch.bool and out.contributed.shape == (60,)
    assert not (out.contributed & ~out.visible).any(), "only visible Gaussians can contribute"
    # A tiny, nearly transparent Gaussian is visible (it covers a tile) but never reaches alpha 1/255.
    faint = Splats(means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]), scales=torch.full((1, 3), 0.05),
                   opacities=torch.tensor([0.002]), sh=torch.zeros(1, 1, 3))
    out = render(on(device, faint), make_camera().to(device))
    assert out.visible.tolist() == [True] and out.contributed.tolist() == [False]


def test_bad_inputs_raise_clear_errors():
    splats = random_splats(5, 0)
    with pytest.raises(ValueError, match="scales must have shape"):
        render(Splats(splats.means, splats.quats, splats.scales[:, :2], splats.opacities, splats.sh), make_camera())
    with pytest.raises(ValueError, match="sh_degree"):
        render(splats, make_camera(), sh_degree=4)
    with pytest.raises(ValueError, match="share one dtype"):
        render(Splats(splats.means, splats.quats.double(), splats.scales, splats.opacities, splats.sh), make_camera())


def test_binning_lists_every_covered_tile_front_to_back(device):
    proj = project_gaussians(*(getattr(on(device, random_splats(80, 2)), p) for p in PARAMS[:4]),
                             make_camera(64, 48).to(device))
    bins = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, 4, 3)
    expected_pairs = int(((proj.tile_max - proj.tile_min).prod(dim=1) * (proj.radii > 0)).sum())
    assert bins.num_pairs == expected_pairs
    for tile in range(12):
        start, end = bins.tile_ranges[tile].tolist()
        ids = bins.gaussian_ids[start:end].long()
        tx, ty = tile % 4, tile // 4
        assert ((proj.tile_min[ids, 0] <= tx) & (tx < proj.tile_max[ids, 0])).all()
        assert ((proj.tile_min[ids, 1] <= ty) & (ty < proj.tile_max[ids, 1])).all()
        assert (proj.depths[ids][1:] >= proj.depths[ids][:-1]).all()


def test_warp_prints_nothing():
    code = ("import torch; from mcsplat.render import render, Splats; from mcsplat.camera import Camera, intrinsics;"
            "w=torch.eye(4); w[2,3]=3; c=Camera(intrinsics(20,20,8,8), w, 16, 16);"
            "render(Splats(torch.zeros(1,3), torch.tensor([[1.,0,0,0]]), torch.full((1,3),.2), torch.tensor([.5]),"
            " torch.zeros(1,1,3)), c)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "" and done.stderr == "", (done.stdout, done.stderr)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the CUDA path is checked on a GPU machine")
def test_cuda_matches_cpu():
    splats = random_splats(500, 31)
    camera = make_camera(width=120, height=90)
    outputs = {}
    for device in ("cpu", "cuda"):
        inputs = leaf(splats, device)
        out = render(inputs, camera.to(device), background=(0.2, 0.2, 0.2), outputs={"median_depth"})
        (out.rgb * 0.5 + out.alpha[..., None]).sum().backward()
        outputs[device] = (out.rgb.detach().cpu(), {p: getattr(inputs, p).grad.cpu() for p in PARAMS},
                           out.median_depth.cpu())
    torch.testing.assert_close(outputs["cuda"][0], outputs["cpu"][0], atol=1e-5, rtol=0)
    torch.testing.assert_close(outputs["cuda"][2], outputs["cpu"][2], atol=1e-4, rtol=1e-5)
    for p in PARAMS:
        assert_close_relative(outputs["cuda"][1][p], outputs["cpu"][1][p], 1e-4, p)


def test_threaded_backward_is_bitwise_reproducible():
    """Training and resume must be exactly repeatable on CPU: the banded backward sums in a fixed order."""
    splats = random_splats(400, 19, log_scale=(-3.0, -2.0))
    camera = make_camera(width=128, height=96, distance=2.5)
    grads = []
    try:
        set_cpu_threads(2, split_small_work=True)
        for _ in range(3):
            inputs = leaf(splats)
            out = render(inputs, camera)
            (out.rgb * torch.linspace(0.2, 1, 3)).sum().backward()
            grads.append([getattr(inputs, p).grad for p in PARAMS])
    finally:
        set_cpu_threads(None)
    for other in grads[1:]:
        assert all(torch.equal(a, b) for a, b in zip(grads[0], other))


def test_block_masks_change_nothing_but_the_work():
    """Binning with 4x4-block masks gives the same image and gradients, bit for bit, as walking every pair."""
    splats = random_splats(300, 23, log_scale=(-4.0, -2.5))
    camera = make_camera(width=96, height=80, distance=2.5)
    proj = project_gaussians(*(getattr(splats, p) for p in PARAMS[:4]), camera)
    from mcsplat.render.project.torch_autograd import view_dependent_colors
    colors = view_dependent_colors(splats.means, splats.sh, camera, 3)
    plain = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, 6, 5)
    masked = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, 6, 5, means2d=proj.means2d,
                           alpha_extent=proj.alpha_extent)
    assert masked.num_pairs < plain.num_pairs and (masked.pair_masks != 0xFFFF).any()
    grads = []
    set_cpu_threads(1)  # with several, the bands (cut by pairs per tile) and so the summation order would differ
    for bins in (plain, masked):
        inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, splats.opacities, colors,
                                                                proj.depths)]
        rgb, alpha, depth, contributed = CompositeFunction.apply(*inputs, torch.tensor([0.1, 0.2, 0.3]), bins, 96, 80)
        (rgb.sum() + alpha.sum() * 0.5 + depth.sum() * 0.1).backward()
        grads.append((rgb.detach(), alpha.detach(), contributed, [t.grad for t in inputs]))
    set_cpu_threads(None)
    assert torch.equal(grads[0][0], grads[1][0]) and torch.equal(grads[0][1], grads[1][1])
    assert torch.equal(grads[0][2], grads[1][2])
    for a, b in zip(grads[0][3], grads[1][3]):
        assert torch.equal(a, b)
