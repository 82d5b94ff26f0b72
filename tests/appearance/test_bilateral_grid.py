"""--appearance bilateral-grid (appearance/bilateral_grid.py, appearance/slicing.py): the Warp slicing kernels
against torch's grid_sample in float64, forward and backward; a grid at identity changes nothing; on a real capture
whose photos were partly vignetted, the grids of those photos learn the vignette (which one affine transform per photo
cannot hold) and the others stay plain."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from mcsplat.appearance import BilateralGridAppearance
from mcsplat.appearance.bilateral_grid import total_variation
from mcsplat.appearance.slicing import slice_grid, slice_reference
from mcsplat.compute.runtime import set_cpu_threads
from mcsplat.config import config_of
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.train import train

from tests.support.helpers import altered_cup


def _random_case(dtype, seed: int, height: int = 37, width: int = 53, shape=(16, 12, 8)):
    generator = torch.Generator().manual_seed(seed)
    columns, rows, levels = shape
    identity = BilateralGridAppearance(1, shape=shape).grid(0).detach()
    grid = (identity + 0.3 * torch.randn(identity.shape, generator=generator)).to(dtype)
    rgb = (torch.rand(height, width, 3, generator=generator) * 1.3 - 0.15).to(dtype)  # some gray outside [0, 1]
    return grid.requires_grad_(), rgb.requires_grad_()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("threads", [1, 2])
def test_slicing_kernels_match_grid_sample_in_float64(seed, threads):
    set_cpu_threads(threads)
    try:
        grid, rgb = _random_case(torch.float64, seed, height=150, width=120)  # 18,000 pixels: 2 ranges with 2 threads
        out, expected = slice_grid(grid, rgb), slice_reference(grid, rgb)
        assert torch.allclose(out, expected, rtol=0, atol=1e-12)
        upstream = torch.randn_like(out)
        grads = torch.autograd.grad(out, (grid, rgb), upstream)
        expected_grads = torch.autograd.grad(expected, (grid, rgb), upstream)
        for got, want in zip(grads, expected_grads):
            assert torch.allclose(got, want, rtol=0, atol=1e-10 * want.abs().max().item())
        # Each range sums its own gradient buffer: the same numbers on every run.
        again = torch.autograd.grad(slice_grid(grid, rgb), (grid, rgb), upstream)
        assert all(torch.equal(a, b) for a, b in zip(grads, again))
    finally:
        set_cpu_threads(None)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the CUDA path is checked on a GPU machine")
def test_slicing_kernels_on_cuda_match_grid_sample():
    grid, rgb = _random_case(torch.float64, 5, height=150, width=120)
    grid, rgb = grid.detach().cuda().requires_grad_(), rgb.detach().cuda().requires_grad_()
    out, expected = slice_grid(grid, rgb), slice_reference(grid, rgb)
    assert torch.allclose(out, expected, rtol=0, atol=1e-12)
    upstream = torch.randn_like(out)
    for got, want in zip(torch.autograd.grad(out, (grid, rgb), upstream),
                         torch.autograd.grad(expected, (grid, rgb), upstream)):
        assert torch.allclose(got, want, rtol=0, atol=1e-10 * want.abs().max().item())


def test_slicing_float32_and_gradcheck():
    grid, rgb = _random_case(torch.float32, 3)
    assert torch.allclose(slice_grid(grid, rgb), slice_reference(grid, rgb), atol=1e-5)
    small_grid, small_rgb = _random_case(torch.float64, 4, height=5, width=7, shape=(3, 2, 4))
    with torch.no_grad():  # keep the brightness off the levels' corners, where the slice is not differentiable
        small_rgb.copy_(small_rgb.clamp(0.05, 0.95))
    assert torch.autograd.gradcheck(slice_grid, (small_grid, small_rgb))


def test_a_grid_at_identity_returns_the_render_and_costs_nothing():
    grids = BilateralGridAppearance(3)
    rgb = torch.rand(30, 40, 3)
    assert torch.allclose(grids(1, rgb), rgb, atol=1e-6)
    assert grids.penalty(2).item() == 0.0 and total_variation(grids.grid(0)).item() == 0.0
    with pytest.raises(ValueError, match="at least 2"):
        slice_grid(torch.zeros(12, 1, 4, 4), rgb)


def _vignette(pixels: np.ndarray) -> np.ndarray:
    """A strong phone-lens vignette: the corners at 40% of the centre's brightness."""
    height, width, _ = pixels.shape
    y, x = np.mgrid[0:height, 0:width]
    radius2 = ((x - width / 2) / (width / 2)) ** 2 + ((y - height / 2) / (height / 2)) ** 2  # 2 at the corners
    return pixels * (1 - 0.3 * radius2)[..., None]


GRID = (4, 4, 2)  # a coarse grid for 100x75 photos (16x16x8 holds more numbers than such a photo has pixels)


def test_the_grids_of_vignetted_photos_learn_their_vignette(shared_data, tmp_path):
    root, vignetted = altered_cup(shared_data, tmp_path / "cup", _vignette)
    config = config_of(data=root, out=tmp_path / "grid", downscale=8, steps=1200, quiet=True, lpips_net="alex",
                         save_every=0, save_renders=False, mcmc=MCMCConfig(cap_max=8000), appearance="bilateral-grid",
                         appearance_grid_shape=GRID, appearance_lr=0.03, appearance_lr_final=0.003)
    print(f"test PSNR (photos without vignette) {train(config)['psnr']:.2f} dB")
    from mcsplat.data import load_scene
    names = [view.name for view in load_scene(root, downscale=8).train]
    state = torch.load(tmp_path / "grid" / "checkpoint.pt", weights_only=True)
    grids = BilateralGridAppearance(len(names), shape=GRID)
    grids.load_state_dict(state["appearance"]["transforms"])
    grey = torch.full((75, 100, 3), 0.5)

    def corner_to_centre(index: int) -> float:
        image = grids(index, grey).mean(dim=-1)
        return (image[:8, :8].mean() / image[33:42, 45:55].mean()).item()

    # The grid of a vignetted photo darkens the corners against the centre; a plain photo's does not.
    darkened = np.median([corner_to_centre(i) for i, n in enumerate(names) if n in vignetted])
    plain = np.median([corner_to_centre(i) for i, n in enumerate(names) if n not in vignetted])
    print(f"corner / centre through the learned grids: vignetted photos {darkened:.3f}, the others {plain:.3f}")
    assert darkened < 0.9 and abs(plain - 1) < 0.1 and darkened < plain - 0.1, (darkened, plain)
