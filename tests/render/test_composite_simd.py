"""The CPU's SIMD compositing kernels against the scalar Warp kernels (the CUDA path) on the same bins."""

from __future__ import annotations

import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.render import render, set_cpu_threads
from mcsplat.render.bin.warp_kernels import bin_gaussians
from mcsplat.render.composite.function import CompositeFunction, cpu_kernels, set_cpu_kernels
from mcsplat.render.project.torch_autograd import project_gaussians, view_dependent_colors

from tests.render.test_render import PARAMS, assert_close_relative, leaf, make_camera, random_splats


def composite_with(kernels: str, splats, camera, background, seed=0):
    """Outputs, last contributors and input gradients of one compositing pass with the named CPU kernels."""
    proj = project_gaussians(*(getattr(splats, p) for p in PARAMS[:4]), camera)
    colors = view_dependent_colors(splats.means, splats.sh, camera, 3)
    tiles = (-(-camera.width // 16), -(-camera.height // 16))
    bins = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, *tiles, means2d=proj.means2d,
                         alpha_extent=proj.alpha_extent)
    inputs = [t.detach().clone().requires_grad_() for t in (proj.means2d, proj.conics, splats.opacities, colors,
                                                            proj.depths)]
    previous = cpu_kernels()
    set_cpu_kernels(kernels)
    try:
        rgb, alpha, depth, contributed = CompositeFunction.apply(*inputs, torch.tensor(background), bins,
                                                                 camera.width, camera.height)
        g = torch.Generator().manual_seed(seed)
        loss = ((rgb * torch.randn(rgb.shape, generator=g)).sum() + (alpha * torch.randn(alpha.shape, generator=g)).sum()
                + (depth * torch.randn(depth.shape, generator=g)).sum())
        loss.backward()
    finally:
        set_cpu_kernels(previous)
    return (rgb.detach(), alpha.detach(), depth.detach(), contributed), [t.grad for t in inputs]


SCENES = {
    # name: (number of Gaussians, log-scale range, opacity range, image size)
    "sparse": (80, (-3.5, -1.5), (0.01, 0.99), (45, 37)),
    "dense, early termination": (600, (-2.5, -1.0), (0.6, 0.999), (64, 48)),
    "tiny splats": (400, (-5.0, -3.5), (0.05, 0.9), (33, 70)),
}


@pytest.mark.parametrize("scene", list(SCENES))
@pytest.mark.parametrize("threads", [1, 2])
def test_simd_kernels_match_scalar_kernels(scene, threads):
    n, log_scale, opacity, (width, height) = SCENES[scene]
    splats = random_splats(n, 5, log_scale=log_scale, opacity=opacity)
    camera = Camera(K=intrinsics(50.0, 52.0, width / 2 + 1.3, height / 2 - 0.7),
                    world_to_camera=make_camera().world_to_camera, width=width, height=height)
    set_cpu_threads(threads, split_small_work=True)
    try:
        (simd_out, simd_grads), (scalar_out, scalar_grads) = (
            composite_with(k, splats, camera, [0.2, 0.5, 0.9], seed=3) for k in ("simd", "scalar"))
    finally:
        set_cpu_threads(None)
    for name, a, b in zip(("rgb", "alpha", "depth"), simd_out[:3], scalar_out[:3]):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-6, msg=name)
    assert torch.equal(simd_out[3], scalar_out[3]), "the same Gaussians must be composited"
    if scene.startswith("dense"):
        assert (1 - simd_out[1]).min() < 1e-3, "the scene must reach the early-termination point"
    for name, a, b in zip(("means2d", "conics", "opacities", "colors", "depths"), simd_grads, scalar_grads):
        assert_close_relative(a, b, 2e-5, name)


def test_simd_path_is_the_default_for_float32_on_cpu_and_float64_keeps_the_scalar_kernels():
    assert cpu_kernels() == "simd"
    splats = random_splats(60, 8)
    float32 = render(leaf(splats), make_camera())
    float64 = render(type(splats)(*(getattr(splats, p).double() for p in PARAMS)), make_camera())
    torch.testing.assert_close(float32.rgb.double(), float64.rgb, atol=2e-6, rtol=0)
    with pytest.raises(ValueError, match="CPU kernels must be one of"):
        set_cpu_kernels("avx")

