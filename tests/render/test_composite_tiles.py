"""The tile kernels (what CUDA runs) on the CPU as cooperative fibers: against the dense reference renderer and the
scalar kernels, float32 and float64, forward and every gradient, median depth, anti-aliasing and pose gradients.

On a GPU machine (`pytest --device cuda`) the same tests run the kernels on CUDA."""

from __future__ import annotations

import contextlib

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.render import render
from mcsplat.render.composite import warp_tiles
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.composite.function import (CompositeFunction, composite, cpu_kernels, cuda_kernels, kernels_for,
                                   set_cpu_kernels, set_cuda_kernels)
from mcsplat.render.project.torch_autograd import project_gaussians, view_dependent_colors
from mcsplat.render.reference import reference_render

from tests.support.helpers import median_gaussian_case
from tests.training.test_pose_refinement import tilted_camera, with_view_grad
from tests.render.test_render import (PARAMS, SEEDS, Splats, assert_close_relative, compare_with_reference,
                                      make_camera, on, random_splats, stacked_on_axis)

DTYPES = [torch.float32, torch.float64]
DTYPE_IDS = ["float32", "float64"]
# The reference renderer sums in another order: float64 agrees to rounding, float32 to its precision.
RTOL = {torch.float32: 1e-4, torch.float64: 1e-9}


@contextlib.contextmanager
def tile_kernels_on(variant: str = "tile"):
    """Composites use the tile kernels wherever they run (`variant` 'tile' or 'tile-all')."""
    previous_cpu, previous_cuda = cpu_kernels(), cuda_kernels()
    set_cpu_kernels("tile")
    set_cuda_kernels(variant)
    try:
        yield
    finally:
        set_cpu_kernels(previous_cpu)
        set_cuda_kernels(previous_cuda)


def camera_of(width: int, height: int) -> Camera:
    return Camera(K=intrinsics(50.0, 52.0, width / 2 + 1.3, height / 2 - 0.7),
                  world_to_camera=make_camera().world_to_camera, width=width, height=height)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("seed", SEEDS)
def test_tile_kernels_match_reference_on_random_scenes(seed, dtype, device):
    with tile_kernels_on():
        fast, _ = compare_with_reference(random_splats(60, seed, dtype=dtype), make_camera(),
                                         background=(0.2, 0.5, 0.9), rtol=RTOL[dtype], seed=seed, device=device)
    assert fast.alpha.max() > 0.5


@pytest.mark.parametrize("variant", ["tile", "tile-all"])
@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tile_kernels_over_many_batches_with_early_termination(dtype, variant, device):
    """More pairs per tile than a forward batch (256) holds, many backward batches (32), pixels that stop early
    beside pixels that walk the whole list, and partial tiles at the image's edge."""
    faint = random_splats(3000, 8, dtype=dtype, log_scale=(-1.8, -1.0), opacity=(0.002, 0.01))
    opaque = random_splats(300, 9, dtype=dtype, log_scale=(-2.8, -2.0), opacity=(0.5, 0.99))
    opaque.means[:, 0] = -opaque.means[:, 0].abs() * 0.6 - 0.1  # on the left: the right half never stops early
    splats = Splats(*(torch.cat([getattr(faint, p), getattr(opaque, p)]) for p in PARAMS))
    camera = camera_of(41, 35)
    with tile_kernels_on(variant):
        fast, _ = compare_with_reference(splats, camera, background=(1.0, 0.4, 0.0), rtol=RTOL[dtype], seed=3,
                                         device=device)
    assert fast.num_pairs / 9 > 2 * warp_tiles.FORWARD_BLOCK, "tiles (3 x 3) must need several forward batches"
    transmittance = 1.0 - fast.alpha.detach()
    assert transmittance.min() < 1e-3 and transmittance.max() > 0.05, "some pixels stop early, others do not"


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tile_kernels_at_the_alpha_clamp_and_stopping_point(dtype, device):
    stack = stacked_on_axis([2.6, 2.8, 3.0, 3.2, 3.4], [0.999] * 5, scale=0.25)
    extra = random_splats(40, 1, dtype=dtype)
    splats = Splats(*(torch.cat([getattr(stack, p).to(dtype), getattr(extra, p)[:, :1] if p == "sh"
                                 else getattr(extra, p)]) for p in PARAMS))
    with tile_kernels_on():
        fast, _ = compare_with_reference(splats, make_camera(), background=(1.0, 1.0, 1.0), rtol=RTOL[dtype],
                                         device=device)
    assert (1.0 - fast.alpha.detach()).min() >= 1e-4 - 1e-6


def _composite_inputs(splats, camera, device):
    proj = project_gaussians(*(getattr(splats, p) for p in PARAMS[:4]), camera)
    colors = view_dependent_colors(splats.means, splats.sh, camera, 3)
    tiles = (-(-camera.width // 16), -(-camera.height // 16))
    bins = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, *tiles, means2d=proj.means2d,
                         alpha_extent=proj.alpha_extent)
    return proj, colors, bins


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tile_forward_is_the_scalar_forward_bit_for_bit(dtype):
    """Per pixel the tile forward does the scalar kernel's arithmetic in its order: the same image to the bit, the
    same last contributors and the same composited Gaussians; the gradients agree to rounding (other sum order)."""
    splats = random_splats(500, 4, dtype=dtype, log_scale=(-3.0, -1.5))
    camera = camera_of(70, 50)
    proj, colors, bins = _composite_inputs(splats, camera, "cpu")
    background = torch.tensor([0.3, 0.6, 0.1], dtype=dtype)
    results = []
    for kernels in ("scalar", "tile"):
        inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, splats.opacities, colors,
                                                                proj.depths)]
        rgb, alpha, depth, contributed = composite(*inputs, background, bins, camera.width, camera.height,
                                                   cpu_kernels=kernels)
        g = torch.Generator().manual_seed(9)
        ((rgb * torch.randn(rgb.shape, generator=g, dtype=dtype)).sum()
         + (alpha * torch.randn(alpha.shape, generator=g, dtype=dtype)).sum()
         + (depth * torch.randn(depth.shape, generator=g, dtype=dtype)).sum()).backward()
        results.append(((rgb, alpha, depth, contributed), [t.grad for t in inputs]))
    (scalar_out, scalar_grads), (tile_out, tile_grads) = results
    for a, b in zip(scalar_out, tile_out):
        assert torch.equal(a, b)
    for name, a, b in zip(("means2d", "conics", "opacities", "colors", "depths"), tile_grads, scalar_grads):
        assert_close_relative(a, b, RTOL[dtype] / 10, name)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("seed", SEEDS[:2])
def test_tile_median_gaussian_is_the_references(seed, dtype, device):
    splats = on(device, random_splats(120, seed, dtype=dtype, log_scale=(-3.0, -1.5)))
    camera = make_camera(width=50, height=40).to(device)
    inputs, expected = median_gaussian_case(splats, camera)
    with tile_kernels_on():
        outputs = composite(*inputs, median_gaussian=True)
        median = render(splats, camera, outputs={"median_depth"}).median_depth
    assert torch.equal(outputs[4].long(), expected)
    torch.testing.assert_close(median, reference_render(splats, camera).median_depth, atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tile_kernels_with_the_anti_aliasing_filter(dtype, device):
    with tile_kernels_on():
        compare_with_reference(random_splats(60, 6, dtype=dtype, log_scale=(-5.0, -2.0)), make_camera(),
                               background=(0.1, 0.1, 0.1), rtol=RTOL[dtype], device=device, antialiased=True)


def test_tile_kernels_give_the_view_matrix_gradient_of_the_reference(device):
    """Pose refinement's gradient (the view matrix's) reaches it through the composite's means2d and conics."""
    splats = random_splats(40, 6, dtype=torch.float64)
    camera = tilted_camera(40, 32)
    fast_camera, reference_camera = with_view_grad(camera, device), with_view_grad(camera, device)
    with tile_kernels_on():
        fast = render(on(device, splats), fast_camera, (0.2, 0.4, 0.6))
    reference = reference_render(on(device, splats), reference_camera, (0.2, 0.4, 0.6))
    torch.testing.assert_close(fast.rgb, reference.rgb, atol=1e-10, rtol=0)
    weights = torch.randn(fast.rgb.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(device)
    (fast.rgb * weights).sum().backward()
    (reference.rgb * weights).sum().backward()
    want = reference_camera.world_to_camera.grad
    assert want.abs().max() > 0
    torch.testing.assert_close(fast_camera.world_to_camera.grad, want, atol=1e-9 * want.abs().max().item(), rtol=1e-7)


def test_cuda_kernel_choice_and_the_cpu_fallbacks():
    x32, x64 = torch.zeros(1), torch.zeros(1, dtype=torch.float64)
    assert kernels_for(x32) == "simd" and kernels_for(x64) == "scalar"
    assert kernels_for(x32, "tile") == "tile" and kernels_for(x64, "tile") == "tile"
    assert cuda_kernels() == "tile"
    with pytest.raises(ValueError, match="CUDA kernels must be one of"):
        set_cuda_kernels("fast")


def test_gradients_land_in_one_buffer_sliced_per_parameter():
    """The backward's ten columns map onto the five inputs, each once (a wrong slice would still run)."""
    columns = sorted(warp_tiles.GRADIENT_COLUMNS.values())
    assert columns[0][0] == 0 and columns[-1][1] == warp_tiles.GRADIENT_WIDTH
    assert all(a[1] == b[0] for a, b in zip(columns, columns[1:]))
    g = torch.Generator().manual_seed(0)
    splats = random_splats(30, 0)
    camera = make_camera()
    proj, colors, bins = _composite_inputs(splats, camera, "cpu")
    inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, splats.opacities, colors,
                                                            proj.depths)]
    with tile_kernels_on():
        rgb, alpha, depth, _ = CompositeFunction.apply(*inputs, torch.zeros(3), bins, camera.width, camera.height)
    (depth * torch.rand(depth.shape, generator=g)).sum().backward()
    # Depth alone: colours get nothing, depths something; the shapes are the inputs' own.
    assert all(t.grad.shape == t.shape for t in inputs)
    assert inputs[3].grad.abs().max() == 0 and inputs[4].grad.abs().max() > 0


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_tile_kernels_compile_for_hopper_gpus_without_one(dtype, tmp_path):
    """Warp's NVRTC builds the CUDA kernels for sm_90 (H100 / H200) on a machine with no GPU, each at the block size
    it is launched with: a kernel that only runs on CPU fibers here at least compiles as CUDA code."""
    import warp as wp

    from mcsplat.compute.runtime import ensure_warp, warp_scalar

    ensure_warp()
    scalar = warp_scalar(dtype)
    kernels = [warp_tiles.forward_kernel(scalar), warp_tiles.forward_kernel(scalar, True),
               warp_tiles.backward_kernel(scalar), warp_tiles.backward_kernel(scalar, False)]
    for kernel in kernels:
        module = kernel.module
        previous = module.options.get("block_dim")
        module.options["block_dim"] = kernel.launch_block_dim
        try:
            (binary,) = wp.compile_aot_module(module, arch=90, module_dir=tmp_path, use_ptx=False)
        finally:
            module.options["block_dim"] = previous
        assert binary.suffix == ".cubin" and binary.stat().st_size > 10_000
        source = binary.with_suffix("").with_suffix(".cu")
        assert f"#define WP_TILE_BLOCK_DIM {kernel.launch_block_dim}" in source.read_text()
