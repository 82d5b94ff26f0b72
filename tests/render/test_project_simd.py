"""The CPU's SIMD projection (render/project/cpu_simd.py, 16 Gaussians per vector) against the float64 truth: in float32
it must be as close to it as the Warp kernel it replaces on the CPU, forward (every output, the screen extent
included) and backward (every gradient, the view matrix's for pose refinement), for every SH degree and option, for
chunks cut short, and with the SH coefficients split or together."""

from __future__ import annotations

import pytest
import torch

from mcsplat.render import Splats, set_cpu_threads
from mcsplat.render.composite.function import set_cpu_kernels
from mcsplat.render.project.warp_kernel import project_and_shade

from tests.training.test_pose_refinement import tilted_camera, with_view_grad
from tests.render.test_render import PARAMS, make_camera
from tests.render.test_warp_kernels import wide_scene

FLOAT_OUTPUTS = ("means2d", "conics", "depths", "alpha_extent")
INT_OUTPUTS = ("radii", "tile_min", "tile_max")


def project(kernels: str, splats: Splats, camera, sh_degree: int, weights, *, split: bool = True, **options):
    """Forward and backward of a random linear function of the outputs with the CPU's `kernels`, on leaf copies of
    `splats` -> (projection, colours, leaves, the view matrix's gradient or None)."""
    leaves = [getattr(splats, p).clone().requires_grad_() for p in PARAMS]
    sh = leaves[4][:, :1] if split else leaves[4]
    sh_rest = leaves[4][:, 1:] if split else None
    set_cpu_kernels(kernels)
    set_cpu_threads(2)
    try:
        projection, colors = project_and_shade(*leaves[:4], sh, camera, sh_degree, sh_rest=sh_rest, **options)
        outputs = [colors, projection.means2d, projection.conics, projection.depths]
        if options.get("antialiased"):
            outputs.append(projection.compensations)
        sum((o * w.to(o.dtype)).sum() for o, w in zip(outputs, weights)).backward()
    finally:
        set_cpu_kernels("simd")
        set_cpu_threads(None)
    view = camera.world_to_camera
    return projection, colors, leaves, (view.grad.clone() if view.requires_grad else None)


def relative_error(value: torch.Tensor, truth: torch.Tensor) -> float:
    """Largest error relative to each entry's size, floored at 1e-3 of the largest (near-zero entries)."""
    truth = truth.double()
    floor = 1e-3 * truth.abs().max().clamp(min=1e-30)
    return ((value.double() - truth).abs() / (truth.abs() + floor)).max().item()


def weights_for(n: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(shape, generator=g, dtype=torch.float64) for shape in ((n, 3), (n, 2), (n, 3), (n,), (n,))]


def assert_as_close_as_the_warp_kernel(simd, warp, truth, names=PARAMS):
    """Each float output and gradient of the SIMD kernels within 2x the Warp kernel's float32 error (or 4e-6, some
    30 float32 roundings) of the float64 truth; the integer outputs differ from the truth's in no more places than
    the Warp kernel's (give or take 2)."""
    projection, colors, leaves = simd[:3]
    warp_projection, warp_colors, warp_leaves = warp[:3]
    truth_projection, truth_colors, truth_leaves = truth[:3]
    pairs = [(name, getattr(projection, name), getattr(warp_projection, name), getattr(truth_projection, name))
             for name in FLOAT_OUTPUTS + ("compensations",) if getattr(truth_projection, name) is not None]
    pairs.append(("colors", colors, warp_colors, truth_colors))
    pairs += [(f"d {name}", a.grad, b.grad, c.grad) for name, a, b, c in zip(names, leaves, warp_leaves, truth_leaves)
              if name != "opacities"]
    for name, ours, theirs, exact in pairs:
        ours_error, theirs_error = relative_error(ours, exact), relative_error(theirs, exact)
        assert ours_error <= max(2.0 * theirs_error, 4e-6), f"{name}: {ours_error:.2e} against {theirs_error:.2e}"
    for name in INT_OUTPUTS:
        exact = getattr(truth_projection, name)
        ours = (getattr(projection, name) != exact).sum().item()
        theirs = (getattr(warp_projection, name) != exact).sum().item()
        assert ours <= theirs + 2, f"{name}: {ours} entries differ from float64 against the Warp kernel's {theirs}"
    assert all(a.grad is None or not a.grad.any() for name, a in zip(names, leaves) if name == "opacities")


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
@pytest.mark.parametrize("options", [{}, {"opacity_aware_radius": True}, {"antialiased": True}])
def test_simd_projection_is_as_close_to_float64_as_the_warp_kernel(sh_degree, options):
    exact = wide_scene(9000, sh_degree)  # 562 chunks and one of 8: the last chunk is cut short
    single = Splats(*(getattr(exact, p).float() for p in PARAMS))
    camera = make_camera(width=70, height=50, distance=3.0)
    weights = weights_for(9000, sh_degree)
    truth = project("scalar", exact, camera, sh_degree, weights, **options)
    simd = project("simd", single, camera, sh_degree, weights, **options)
    warp = project("scalar", single, camera, sh_degree, weights, **options)
    assert_as_close_as_the_warp_kernel(simd, warp, truth)
    shown = (simd[0].radii > 0).sum().item()
    assert 100 < shown < 8900, "the scene has Gaussians culled and Gaussians shown"
    # SH bands above the degree get no gradient (the backward writes them: its buffers are not zero-filled).
    assert not simd[2][4].grad[:, (sh_degree + 1) ** 2:].any()


@pytest.mark.parametrize("n", [1, 15, 16, 17, 40])
@pytest.mark.parametrize("split", [True, False])
def test_simd_projection_of_short_chunks_and_either_sh_layout(n, split):
    exact = wide_scene(n, n, dtype=torch.float64)
    exact.means[::2] = exact.means[::2] * 0.3  # in front of the camera, so that some are shown
    single = Splats(*(getattr(exact, p).float() for p in PARAMS))
    camera = make_camera(width=40, height=30, distance=3.0)
    weights = weights_for(n, n)
    runs = [project(kernels, splats, camera, 3, weights, split=split)
            for kernels, splats in (("scalar", exact), ("simd", single), ("scalar", single))]
    assert_as_close_as_the_warp_kernel(runs[1], runs[2], runs[0])


def test_simd_projection_writes_zeros_for_gaussians_no_gradient_reaches():
    exact = wide_scene(200, 5)
    single = Splats(*(getattr(exact, p).float() for p in PARAMS))
    camera = make_camera(width=70, height=50, distance=3.0)
    weights = weights_for(200, 5)
    unreached = torch.zeros(200, dtype=torch.bool)
    unreached[40:90] = True  # three whole chunks (48-95) and parts of two
    for w in weights:
        w[unreached] = 0.0
    _, _, leaves, _ = project("simd", single, camera, 3, weights)
    for name, leaf in zip(PARAMS, leaves):
        if leaf.grad is not None:
            assert not leaf.grad[unreached].any(), name
            assert leaf.grad[~unreached].any(), name


@pytest.mark.parametrize("antialiased", [False, True])
def test_simd_view_matrix_gradient_is_as_close_to_float64_as_the_warp_kernel(antialiased):
    exact = wide_scene(5000, 2)
    single = Splats(*(getattr(exact, p).float() for p in PARAMS))
    camera = tilted_camera(70, 50)
    weights = weights_for(5000, 7)
    options = {"antialiased": antialiased}
    truth = project("scalar", exact, with_view_grad(camera, "cpu"), 3, weights, **options)
    float_camera = tilted_camera(70, 50, dtype=torch.float32)
    simd = project("simd", single, with_view_grad(float_camera, "cpu"), 3, weights, **options)
    warp = project("scalar", single, with_view_grad(float_camera, "cpu"), 3, weights, **options)
    assert_as_close_as_the_warp_kernel(simd, warp, truth)
    ours, theirs = relative_error(simd[3], truth[3]), relative_error(warp[3], truth[3])
    assert ours <= max(2.0 * theirs, 4e-6), f"view gradient: {ours:.2e} against {theirs:.2e}"
