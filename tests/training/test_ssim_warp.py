"""The fused Warp SSIM (ssim/warp.py) against the torch SSIM of losses.py in float64: the same value and gradient.

The kernels are meant for CUDA but are plain Warp code, so they run on the CPU too: every test runs there, and on
CUDA as well when a GPU is present."""

from __future__ import annotations

import pytest
import torch

from mcsplat import losses
from mcsplat.ssim.warp import KERNELS, fused_ssim_warp, fused_ssim_warp_applies

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def pair(height, width, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(height, width, 3, generator=g)
    image = (target + 0.15 * torch.randn(height, width, 3, generator=g)).clamp(0, 1)
    return image.to(device), target.to(device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [(7, 5), (64, 48), (1, 30), (37, 45), (11, 12)])
def test_value_and_gradient_match_torch_in_float64(device, size):
    image, target = pair(*size, device=device)
    fused_in = image.clone().requires_grad_()
    reference_in = image.double().requires_grad_()
    value = fused_ssim_warp(fused_in, target)
    expected = losses.ssim_map(reference_in, target.double()).mean()
    assert value.dtype == torch.float32 and value.shape == ()
    assert abs(value.item() - expected.item()) <= 1e-5 * abs(expected.item())
    # A grad_output other than one: the backward must scale by it.
    (value * 3.0).backward()
    (expected * 3.0).backward()
    error = (fused_in.grad.double() - reference_in.grad).abs().max() / reference_in.grad.abs().max()
    assert error < 1e-4, f"gradient differs by {error:.1e} of its largest magnitude"


@pytest.mark.parametrize("device", DEVICES)
def test_a_non_contiguous_image_gives_the_same_result(device):
    image, target = pair(20, 24, seed=3, device=device)
    strided = image.permute(1, 0, 2).contiguous().permute(1, 0, 2).requires_grad_()  # [H, W, 3], not contiguous
    contiguous = image.clone().requires_grad_()
    fused_ssim_warp(strided, target).backward()
    fused_ssim_warp(contiguous, target).backward()
    assert torch.equal(strided.grad, contiguous.grad)


@pytest.mark.parametrize("device", DEVICES)
def test_identical_images_have_ssim_one_and_zero_gradient(device):
    _, target = pair(40, 33, seed=2, device=device)
    x = target.clone().requires_grad_()
    value = fused_ssim_warp(x, target)
    value.backward()
    assert abs(value.item() - 1.0) < 1e-6 and x.grad.abs().max() < 1e-5


def test_losses_take_the_warp_kernels_on_cuda_only():
    image, target = pair(8, 8)
    assert not fused_ssim_warp_applies(image, target)  # the CPU keeps ssim_cpu
    assert losses.training_kernels(torch.device("cuda")) == KERNELS
    assert losses.training_kernels(torch.device("cuda"), torch.float64) == []
    if torch.cuda.is_available():
        image, target = image.cuda(), target.cuda()
        assert fused_ssim_warp_applies(image, target)
        assert not fused_ssim_warp_applies(image.double(), target.double())
        assert not fused_ssim_warp_applies(image, target.clone().requires_grad_())
        assert torch.equal(losses.ssim(image, target), fused_ssim_warp(image, target))


def test_wrong_inputs_are_refused():
    image, target = pair(8, 8)
    with pytest.raises(TypeError):
        fused_ssim_warp(image.double(), target.double())
    with pytest.raises(ValueError):
        fused_ssim_warp(image[..., :2], target[..., :2])
