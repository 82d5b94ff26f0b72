"""The MCMC position noise in one pass on the CPU: means += factor x gate(o) x Sigma eta for 16 Gaussians at a time.

strategy/noise.py's torch form takes eleven operators over the Gaussians a step (the opacities, the gate's sigmoids,
the scales' exp, the covariance product, the products and the sum: about 1.5 ms at 100k on two cores); here one
kernel reads the stored parameters (quaternions, log-scales, opacity logits) and the drawn eta, and adds the noise
to the positions in place. The draw itself stays torch's, from the strategy's generator, so a seed gives the noise it
gave. The exponentials are a polynomial (relative error about 1e-7) instead of torch's: the moved positions agree
with the torch form to float32 rounding, not to the bit.
"""

from __future__ import annotations

import torch
import warp as wp

from ..compute.cpp_snippets import read_snippet
from ..compute.cpu_target import kernel_flags
from ..compute.runtime import ensure_warp, flat_view, run_ranges
from ..compute.simd_lanes import LANES, VECTOR_TYPES, lanes_in, lanes_out
from ..render.kernel_choice import kernels_for

_SOURCE = read_snippet(__package__, "position_noise_simd.cpp", {
    "VECTOR_TYPES": VECTOR_TYPES, "LANES": LANES, "LOAD_M": lanes_in("m", "means_", 3),
    "LOAD_E": lanes_in("e", "eta_", 3), "LOAD_Q": lanes_in("q", "quats_", 4),
    "LOAD_S": lanes_in("log_s", "log_scales_", 3), "STORE_M": lanes_out(["m[0]", "m[1]", "m[2]"], "means_")})

wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512")})
_floats = wp.array(dtype=wp.float32)


@wp.func_native(_SOURCE)
def _noise_chunk(chunk: int, n: int, means: _floats, quats: _floats, log_scales: _floats, opacity_logits: _floats,
                 eta: _floats, factor: float, covariance: int, gated: int, gate_k: float, gate_center: float): ...


@wp.kernel
def position_noise_simd(first_chunk: int, n: int, means: _floats, quats: _floats, log_scales: _floats,
                        opacity_logits: _floats, eta: _floats, factor: float, covariance: int, gated: int,
                        gate_k: float, gate_center: float):
    """One thread per chunk of LANES Gaussians; each writes only its own rows of `means`."""
    _noise_chunk(first_chunk + wp.tid(), n, means, quats, log_scales, opacity_logits, eta, factor, covariance, gated,
                 gate_k, gate_center)


KERNELS = [position_noise_simd]


def takes(params: dict[str, torch.Tensor], factor: float | torch.Tensor) -> bool:
    """Whether the kernel serves these parameters: float32, contiguous, where the renderer runs the CPU's own kernels
    (kernel_choice: not while the CPU stands in for CUDA), and a factor the host holds."""
    tensors = [params[key] for key in ("means", "quats", "log_scales", "opacity_logits")]
    return (kernels_for(tensors[0]) == "simd" and all(t.dtype == torch.float32 and t.is_contiguous() for t in tensors)
            and (not isinstance(factor, torch.Tensor) or factor.device.type == "cpu"))


def add_position_noise(params: dict[str, torch.Tensor], eta: torch.Tensor, factor: float | torch.Tensor, *,
                       covariance: bool, gated: bool, gate_k: float, gate_center: float) -> None:
    """params["means"] += factor x sigmoid(-gate_k (sigmoid(logit) - gate_center)) x Sigma eta, in place (`takes`
    says where; the gate is 1 without `gated`, Sigma the identity without `covariance`)."""
    ensure_warp()
    means = params["means"]
    n = means.shape[0]
    eta = eta.contiguous()
    run_ranges(position_noise_simd, -(-n // LANES), means.device, [
        n, *(flat_view(params[key]) for key in ("means", "quats", "log_scales", "opacity_logits")), flat_view(eta),
        float(factor), int(covariance), int(gated), float(gate_k), float(gate_center)], 4096 // LANES)
