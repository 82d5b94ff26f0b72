"""The MCMC position noise in one pass on the CPU: means += factor x gate(o) x Sigma eta for 16 Gaussians at a time.

strategy/noise.py's torch form takes a dozen operators over the Gaussians a step (the draw, the opacities, the gate's
sigmoids, the scales' exp, the covariance product, the products and the sum: about 3 ms at 100k on two cores, 40%
of it torch's normal draw); here one kernel reads the stored parameters (quaternions, log-scales, opacity logits),
draws eta itself and adds the noise to the positions in place.

The draw (normals_simd.h) is counter-based: eta of Gaussian i is a function of the step's key and i alone, the key
drawn from the strategy's generator (so a seed, and a resumed generator, give the same noise, on any number of
threads). `fill_normals` writes the same numbers out, for the tests. The exponentials and the logarithm are
polynomials (relative error about 1e-7): the positions agree with the torch form given the same eta to float32
rounding, not to the bit.
"""

from __future__ import annotations

import torch
import warp as wp

from ..compute.cpp_snippets import read_snippet
from ..compute.cpu_target import kernel_flags
from ..compute.runtime import ensure_warp, flat_view, run_ranges
from ..compute.simd_lanes import LANES, SIMD_MATH, VECTOR_TYPES, lanes_in, lanes_out
from ..geometry.covariance import COVARIANCE_LANES
from ..render.kernel_choice import simd_serves

_NORMALS = read_snippet(__package__, "normals_simd.h", {"LANES": LANES})
_SOURCE = read_snippet(__package__, "position_noise_simd.cpp", {
    "VECTOR_TYPES": VECTOR_TYPES, "SIMD_MATH": SIMD_MATH, "COVARIANCE": COVARIANCE_LANES, "LANES": LANES,
    "NORMALS": _NORMALS, "LOAD_M": lanes_in("m", "means_", 3),
    "LOAD_Q": lanes_in("q", "quats_", 4), "LOAD_S": lanes_in("log_s", "log_scales_", 3),
    "STORE_M": lanes_out(["m[0]", "m[1]", "m[2]"], "means_")})
_FILL = read_snippet(__package__, "normals_fill_simd.cpp", {
    "VECTOR_TYPES": VECTOR_TYPES, "SIMD_MATH": SIMD_MATH, "LANES": LANES, "NORMALS": _NORMALS,
    "STORE_ETA": lanes_out(["eta[0]", "eta[1]", "eta[2]"], "out_")})
KEY_BITS = 62  # a draw's key: a number below 2^62 from the strategy's generator

wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512")})
_floats = wp.array(dtype=wp.float32)
_keys = wp.array(dtype=wp.int64)  # the draw's key: one number, read by the kernel (the host reads nothing)


@wp.func_native(_SOURCE)
def _noise_chunk(chunk: int, n: int, means: _floats, quats: _floats, log_scales: _floats, opacity_logits: _floats,
                 key: _keys, factor: float, covariance: int, gated: int, gate_k: float, gate_center: float): ...


@wp.func_native(_FILL)
def _fill_chunk(chunk: int, n: int, key: _keys, out: _floats): ...


@wp.kernel
def position_noise_simd(first_chunk: int, n: int, means: _floats, quats: _floats, log_scales: _floats,
                        opacity_logits: _floats, key: _keys, factor: float, covariance: int, gated: int,
                        gate_k: float, gate_center: float):
    """One thread per chunk of LANES Gaussians; each writes only its own rows of `means`."""
    _noise_chunk(first_chunk + wp.tid(), n, means, quats, log_scales, opacity_logits, key, factor, covariance, gated,
                 gate_k, gate_center)


@wp.kernel
def normals_simd(first_chunk: int, n: int, key: _keys, out: _floats):
    """The position noise's eta for rows [0, n) of `out` [n, 3], one thread per chunk of LANES rows."""
    _fill_chunk(first_chunk + wp.tid(), n, key, out)


KERNELS = [position_noise_simd]


def takes(params: dict[str, torch.Tensor], factor: float | torch.Tensor) -> bool:
    """Whether the kernel serves these parameters: float32, contiguous, where the renderer runs the CPU's own kernels
    (kernel_choice: not while the CPU stands in for CUDA), and a factor the host holds."""
    return (simd_serves(*(params[key] for key in ("means", "quats", "log_scales", "opacity_logits")))
            and (not isinstance(factor, torch.Tensor) or factor.device.type == "cpu"))


def draw_key(generator: torch.Generator) -> torch.Tensor:
    """A draw's key: one number below 2^62 from the strategy's generator, as a tensor of one (the generator moves on
    by the same amount each step, whatever the count)."""
    return torch.randint(0, 2**KEY_BITS, (1,), generator=generator, dtype=torch.int64)


def add_position_noise(params: dict[str, torch.Tensor], key: torch.Tensor, factor: float | torch.Tensor, *,
                       covariance: bool, gated: bool, gate_k: float, gate_center: float) -> None:
    """params["means"] += factor x sigmoid(-gate_k (sigmoid(logit) - gate_center)) x Sigma eta, in place, eta the
    draw of `key` (`fill_normals`; `takes` says where; the gate is 1 without `gated`, Sigma the identity without
    `covariance`)."""
    ensure_warp()
    means = params["means"]
    n = means.shape[0]
    run_ranges(position_noise_simd, -(-n // LANES), means.device, [
        n, *(flat_view(params[name]) for name in ("means", "quats", "log_scales", "opacity_logits")), flat_view(key),
        float(factor), int(covariance), int(gated), float(gate_k), float(gate_center)], 4096 // LANES)


def fill_normals(n: int, key: torch.Tensor | int) -> torch.Tensor:
    """[n, 3] float32: the eta that add_position_noise draws for Gaussians 0 .. n - 1 with `key`."""
    ensure_warp()
    out = torch.empty(n, 3)
    key = torch.as_tensor(key, dtype=torch.int64).reshape(1)
    run_ranges(normals_simd, -(-n // LANES), out.device, [n, flat_view(key), flat_view(out)], 4096 // LANES)
    return out
