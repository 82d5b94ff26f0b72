"""The fused CPU SSIM (ssim/cpu.py) against the torch SSIM of losses.py: the same value and gradient."""

from __future__ import annotations

import pytest
import torch

from mcsplat.losses import photometric_loss, ssim, ssim_map
from mcsplat.render import set_cpu_threads
from mcsplat.ssim.cpu import fused_ssim, fused_ssim_applies


def pair(height, width, seed=0):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(height, width, 3, generator=g)
    image = (target + 0.15 * torch.randn(height, width, 3, generator=g)).clamp(0, 1)
    return image, target


@pytest.mark.parametrize("size", [(37, 45), (5, 8), (1, 30), (64, 17)])
def test_fused_ssim_matches_torch_value_and_gradient(size):
    image, target = pair(*size)
    fused_in, torch_in = image.clone().requires_grad_(), image.clone().requires_grad_()
    value = fused_ssim(fused_in, target)
    expected = ssim_map(torch_in, target).mean()
    torch.testing.assert_close(value, expected, atol=2e-6, rtol=0)
    (value * 3.0).backward()
    (expected * 3.0).backward()
    error = (fused_in.grad - torch_in.grad).abs().max() / torch_in.grad.abs().max()
    assert error < 1e-5, f"gradient differs by {error:.1e} of its largest magnitude"


@pytest.mark.parametrize("size", [(37, 45), (150, 203), (70, 3840)])
def test_the_fused_photometric_loss_matches_torch_in_float64(size):
    """L1 and SSIM from one fused pass (the training loss on the CPU) against the torch definitions in float64,
    with the image cut into row ranges (two threads) whose borders the window crosses; 3840 wide: each range's room
    for its rows (ssim_cpu's scratch) at the width of a 4K photo."""
    image, target = pair(*size, seed=3)
    image[:4, :6] = target[:4, :6]  # equal pixels: |x - y| has no slope there, in torch as here
    fused = image.clone().requires_grad_()
    reference = image.double().requires_grad_()
    try:
        set_cpu_threads(2, split_small_work=True)
        loss = photometric_loss(fused, target, ssim_weight=0.2)
        loss.backward()
    finally:
        set_cpu_threads(None)
    expected = 0.8 * (reference - target.double()).abs().mean() + \
        0.2 * (1.0 - ssim_map(reference, target.double()).mean())
    expected.backward()
    assert abs(loss.item() - expected.item()) < 2e-6
    error = (fused.grad.double() - reference.grad).abs().max() / reference.grad.abs().max()
    assert error < 1e-5, f"gradient differs by {error:.1e} of its largest magnitude"


def test_fused_ssim_is_the_cpu_float32_path_and_does_not_depend_on_threads():
    image, target = pair(120, 90, seed=1)
    assert fused_ssim_applies(image, target)
    assert not fused_ssim_applies(image.double(), target.double())
    assert not fused_ssim_applies(image, target.clone().requires_grad_())
    results = []
    try:
        for threads in (1, 2):
            set_cpu_threads(threads, split_small_work=True)
            x = image.clone().requires_grad_()
            photometric_loss(x, target).backward()
            results.append((ssim(x, target).detach(), x.grad))
    finally:
        set_cpu_threads(None)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_identical_images_have_ssim_one_and_zero_gradient():
    _, target = pair(40, 40, seed=2)
    x = target.clone().requires_grad_()
    value = fused_ssim(x, target)
    value.backward()
    assert abs(value.item() - 1.0) < 1e-6 and x.grad.abs().max() < 1e-5
