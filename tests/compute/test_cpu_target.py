"""The CPU the kernels are built for (compute/cpu_target.py) and the SIMD kernels' vector width: a build for another
CPU (MCSPLAT_CPU_TARGET) and another width (MCSPLAT_SIMD_LANES) give the host build's results, so that what
benchmarks/train_speed.py --builds times is the same computation."""

import json
import os
import subprocess
import sys

import pytest

from mcsplat.compute.cpu_target import NATIVE, TARGET_VARIABLE, kernel_flags, target_flag, with_target
from mcsplat.errors import MCSplatError

# Sigma v for random Gaussians through the CPU's SIMD kernel, in a process of its own (the build and the width are
# chosen at import), against the float64 product: the largest error relative to |Sigma v|.
COVARIANCE_ERROR = """
import json, torch
from mcsplat.compute.simd_lanes import LANES
from mcsplat.geometry.covariance import covariance_times
g = torch.Generator().manual_seed(0)
n = 1000 + 7  # a short last chunk at every width
quats, scales = torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) + 0.05
vectors = torch.randn(n, 3, generator=g)
got = covariance_times(quats, scales, vectors).double()
q = torch.nn.functional.normalize(quats.double(), dim=1)
w, x, y, z = q.unbind(1)
rotation = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(n, 3, 3)
sigma = rotation @ torch.diag_embed(scales.double() ** 2) @ rotation.transpose(1, 2)
want = (sigma @ vectors.double()[:, :, None])[:, :, 0]
print(json.dumps({"lanes": LANES, "error": float(((got - want).norm(dim=1) / want.norm(dim=1)).max())}))
"""


def test_the_target_is_the_host_unless_named(monkeypatch):
    monkeypatch.delenv(TARGET_VARIABLE, raising=False)
    assert target_flag() == NATIVE == "-march=native"
    assert kernel_flags("-ffp-contract=fast") == "-march=native -ffp-contract=fast"
    assert with_target("-march=native -mllvm=-x") == "-march=native -mllvm=-x"
    monkeypatch.setenv(TARGET_VARIABLE, "znver3")
    assert kernel_flags("-ffp-contract=fast") == "-target-cpu znver3 -ffp-contract=fast"
    assert with_target("-march=native -mllvm=-x") == "-target-cpu znver3 -mllvm=-x"
    assert with_target("") == "-target-cpu znver3" and with_target(None) is None
    monkeypatch.setenv(TARGET_VARIABLE, "znver3; rm -rf /")
    with pytest.raises(MCSplatError, match="not a CPU name"):
        target_flag()


@pytest.mark.parametrize("build", [{}, {TARGET_VARIABLE: "haswell", "MCSPLAT_SIMD_LANES": "8"}],
                         ids=["host-16-lanes", "avx2-8-lanes"])
def test_another_build_and_width_compute_the_same(build):
    """haswell: AVX2 without AVX-512 on any x86 host (an x86 machine is assumed: the CI's and ours)."""
    env = {**os.environ, **build}
    run = subprocess.run([sys.executable, "-c", COVARIANCE_ERROR], env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["lanes"] == int(build.get("MCSPLAT_SIMD_LANES", 16))
    assert result["error"] < 1e-5, result
