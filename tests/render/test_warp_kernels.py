"""Projection + SH and binning as Warp kernels, against the torch versions they replaced (project/torch_autograd.py and
bin/torch_oracle.py): the same values, the same gradients, the same lists."""

from __future__ import annotations

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.render import set_cpu_threads
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.bin.torch_oracle import torch_bin_gaussians
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.render.project.torch_autograd import project_gaussians, view_dependent_colors
from mcsplat.render.project.warp_kernel import project_and_shade

from tests.render.test_render import PARAMS, make_camera, on, random_splats

OUTPUTS = ("means2d", "conics", "depths", "radii", "tile_min", "tile_max", "alpha_extent")


def wide_scene(n: int, seed: int, dtype=torch.float64):
    """Gaussians in front of, around and behind the camera (culled; clamped Jacobian), some with tiny quaternions."""
    splats = random_splats(n, seed, dtype=dtype, spread=4.0, log_scale=(-4.0, -0.5))
    splats.quats[::97] *= 1e-14  # under the normalisation's clamp
    return splats


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("opacity_aware_radius", [False, True])
def test_projection_kernel_matches_torch_in_float64(sh_degree, opacity_aware_radius, device):
    splats = on(device, wide_scene(9000, sh_degree))  # over 2 x 4096: the CPU splits the Gaussians into ranges
    camera = make_camera(width=70, height=50, distance=3.0).to(device)
    kernel_in = [getattr(splats, p).clone().requires_grad_() for p in PARAMS]
    torch_in = [getattr(splats, p).clone().requires_grad_() for p in PARAMS]
    set_cpu_threads(2, split_small_work=True)
    try:
        projection, colors = project_and_shade(*kernel_in, camera, sh_degree, opacity_aware_radius=opacity_aware_radius)
    finally:
        set_cpu_threads(None)
    expected = project_gaussians(*torch_in[:4], camera, opacity_aware_radius=opacity_aware_radius)
    expected_colors = view_dependent_colors(torch_in[0], torch_in[4], camera, sh_degree)
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(projection, name), getattr(expected, name), atol=1e-12, rtol=1e-12,
                                   msg=name)
    torch.testing.assert_close(colors, expected_colors, atol=1e-12, rtol=0)
    assert (projection.radii == 0).sum() > 100 and (projection.radii > 0).sum() > 100

    g = torch.Generator().manual_seed(sh_degree)
    weights = [torch.randn(t.shape, generator=g, dtype=t.dtype).to(device) for t in (colors, *(getattr(expected, k) for k in
                                                                                 ("means2d", "conics", "depths")))]
    for outs, inputs in (((colors, projection.means2d, projection.conics, projection.depths), kernel_in),
                         ((expected_colors, expected.means2d, expected.conics, expected.depths), torch_in)):
        sum((o * w).sum() for o, w in zip(outs, weights)).backward()
    for name, a, b in zip(PARAMS, kernel_in, torch_in):
        if name == "opacities":
            assert a.grad is None or not a.grad.any(), "opacity enters only the non-differentiable extents"
            continue
        torch.testing.assert_close(a.grad, b.grad, atol=1e-10 * b.grad.abs().max().item(), rtol=1e-9, msg=name)


def test_projection_kernel_gradcheck_float64(device):
    splats = on(device, random_splats(12, 4, dtype=torch.float64))
    camera = make_camera(width=30, height=24).to(device)
    inputs = tuple(getattr(splats, p).clone().requires_grad_() for p in ("means", "quats", "scales", "sh"))

    def f(means, quats, scales, sh):
        projection, colors = project_and_shade(means, quats, scales, splats.opacities, sh, camera, 3)
        return projection.means2d, projection.conics, projection.depths, colors

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-7, rtol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("masks", [True, False])
@pytest.mark.parametrize("kernels", ["simd", "scalar"])  # the CPU's C++ loops, or the Warp kernels CUDA runs
def test_binning_kernels_match_torch_binning(dtype, masks, kernels, device):
    if kernels == "scalar" and device.type == "cuda":
        pytest.skip("the CPU's choice of kernels: CUDA runs the Warp kernels either way")
    splats = on(device, random_splats(3000, 9, dtype=dtype, spread=1.5, log_scale=(-5.0, -1.5)))
    camera = Camera(K=intrinsics(90.0, 90.0, 61.0, 47.0), world_to_camera=make_camera().world_to_camera,
                    width=120, height=90).to(device)
    p = project_gaussians(*(getattr(splats, name) for name in PARAMS[:4]), camera)
    p.depths.data[::50] = p.depths.data[1::50][:p.depths[::50].numel()]  # equal depths: ties go by index
    extra = dict(means2d=p.means2d, alpha_extent=p.alpha_extent) if masks else {}
    set_cpu_kernels(kernels)
    try:
        bins = bin_gaussians(p.tile_min, p.tile_max, p.depths, p.radii, 8, 6, **extra).listed()
    finally:
        set_cpu_kernels("simd")
    expected = torch_bin_gaussians(p.tile_min, p.tile_max, p.depths, p.radii, 8, 6, **extra)
    assert bins.num_pairs == expected.num_pairs > 3000
    assert torch.equal(bins.tile_ranges, expected.tile_ranges)
    assert torch.equal(bins.gaussian_ids, expected.gaussian_ids)
    if dtype == torch.float32 or not masks:
        assert torch.equal(bins.pair_masks, expected.pair_masks)
    else:  # float64 spans are evaluated in float32: a bit may differ only where the box edge meets a pixel centre
        assert (bins.pair_masks != expected.pair_masks).float().mean() < 1e-3


@pytest.mark.parametrize("n", [0, 5])
def test_binning_with_nothing_visible(n, device):
    zeros = torch.zeros(n, 2, dtype=torch.int32, device=device)
    bins = bin_gaussians(zeros, zeros, torch.ones(n, device=device), torch.zeros(n, dtype=torch.int32, device=device),
                         3, 2)
    assert bins.num_pairs == 0 and bins.tile_ranges.shape == (6, 2) and not bins.tile_ranges.any()


def test_compile_kernels_leaves_nothing_to_compile(tmp_path, device):
    import warp as wp

    from mcsplat.compute.compile import compile_kernels, modules_to_compile
    from mcsplat.step import step_kernels

    kernels = step_kernels(device)
    compile_kernels(kernels, device)
    assert modules_to_compile(kernels, device) == 0
    cache = wp.config.kernel_cache_dir
    wp.config.kernel_cache_dir = str(tmp_path)  # an empty cache: every module would need a compile
    try:
        assert modules_to_compile(kernels, device) >= 3  # projection, binning and compositing at least
    finally:
        wp.config.kernel_cache_dir = cache


def test_split_sh_of_a_model_renders_like_the_concatenated_coefficients(device):
    """GaussianModel hands render() sh0 and shN apart; the image and every gradient match the concatenated path."""
    from mcsplat.gaussians import GaussianModel
    from mcsplat.render import Splats, render

    splats = on(device, random_splats(200, 12))
    g = torch.Generator().manual_seed(3)
    model = GaussianModel(splats.means, torch.log(splats.scales), splats.quats, torch.logit(splats.opacities),
                          splats.sh[:, :1].clone(), splats.sh[:, 1:].clone())
    camera = make_camera().to(device)
    weights = torch.randn(camera.height, camera.width, 3, generator=g).to(device)
    split = render(model, camera, background=(0.1, 0.2, 0.3))
    (split.rgb * weights).sum().backward()
    together = Splats(model.means.detach(), model.quats.detach(), model.scales.detach(), model.opacities.detach(),
                      model.sh.detach().clone().requires_grad_())
    joined = render(together, camera, background=(0.1, 0.2, 0.3))
    (joined.rgb * weights).sum().backward()
    assert torch.equal(split.rgb, joined.rgb)
    # Bit for bit on the CPU; CUDA's backward adds with atomics, in an order that changes from run to run.
    same = torch.equal if device.type == "cpu" else lambda a, b: torch.allclose(a, b, rtol=1e-5, atol=1e-7)
    assert same(model.params["sh0"].grad, together.sh.grad[:, :1])
    assert same(model.params["shN"].grad, together.sh.grad[:, 1:])


def test_covariance_times_matches_the_batched_matrix_product(device):
    from mcsplat.geometry.covariance import covariance_times
    from mcsplat.geometry.rotation import covariance_3d

    g = torch.Generator().manual_seed(5)
    n = 10_000  # several ranges of the CPU thread pool
    quats, scales = torch.randn(n, 4, generator=g, dtype=torch.float64), torch.rand(n, 3, generator=g) + 0.1
    vectors = torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats, scales, vectors = quats.to(device), scales.to(device), vectors.to(device)
    set_cpu_threads(2, split_small_work=True)
    try:
        got = covariance_times(quats, scales.double(), vectors)
    finally:
        set_cpu_threads(None)
    expected = torch.bmm(covariance_3d(quats, scales.double()), vectors[:, :, None])[:, :, 0]
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("n", [10_003, 7])  # full chunks of 16 and a short one; a single short chunk
def test_covariance_times_in_float32_is_float32_close_to_float64(n, device):
    """On the CPU float32 takes the SIMD kernel (16 Gaussians per vector), on CUDA the Warp kernel; either way the
    float64 product to float32's precision, quaternions under the normalisation's clamp included."""
    from mcsplat.geometry.covariance import covariance_times
    from mcsplat.geometry.rotation import covariance_3d

    g = torch.Generator().manual_seed(n)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    quats[::101] *= 1e-14
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) + 0.1
    vectors = torch.randn(n, 3, generator=g, dtype=torch.float64)
    set_cpu_threads(2, split_small_work=True)
    try:
        got = covariance_times(*(t.float().to(device) for t in (quats, scales, vectors))).cpu().double()
    finally:
        set_cpu_threads(None)
    exact = torch.bmm(covariance_3d(quats, scales), vectors[:, :, None])[:, :, 0]
    size = scales.max(dim=1).values ** 2 * vectors.norm(dim=1)  # |Sigma v| is at most this
    assert ((got - exact).norm(dim=1) / size).max() < 1e-6


def test_the_projection_reads_a_moved_cameras_numbers_from_its_host_copy():
    """A camera moved to the GPU keeps the host copy it came from, and the projection's scalar arguments are read
    from it: reading them from device tensors would wait for every kernel queued before (a stall per render). The
    "meta" device has no data at all, so any read from the moved tensors would fail here."""
    from mcsplat.render.project.warp_kernel import _camera_arguments

    camera = make_camera(width=40, height=30)
    moved = camera.to("meta")
    assert moved.K.device.type == "meta" and moved.on_host() is camera and camera.on_host() is camera
    assert moved.to("meta").on_host() is camera
    expected = _camera_arguments(camera, 0.01, 100.0, 0.3)
    assert _camera_arguments(moved, 0.01, 100.0, 0.3) == expected
    # A camera made from device tensors (a pose being refined) has no host copy and is read where it is.
    assert type(moved)(K=moved.K, world_to_camera=moved.world_to_camera, width=40, height=30).on_host() is None
