"""Quaternion rotations and the 3D covariance applied to vectors, as Warp code (CPU and CUDA).

`rotation_function(dtype)` is the rotation matrix of a unit (w, x, y, z) quaternion, shared by the projection kernels.
`covariance_times(quats, scales, vectors)` computes Sigma_i v_i = R_i S_i^2 R_i^T v_i for every Gaussian, the hot
spot of the MCMC position noise: torch's batched 3x3 products were more than an order of magnitude slower than a
Warp thread per Gaussian, and the CPU's float32 SIMD version (16 Gaussians per vector) takes less than half of that
again (docs/measurements-log.md, "CPU kernels (rasterizer.py, train_speed.py), 2026-11-22", and
benchmarks/results/train_speed/2026-11-27-kernels-side-by-side.md, "The pieces alone").
"""

import functools

import torch
import warp as wp

from ..compute.cpp_snippets import read_snippet
from ..compute.cpu_target import kernel_flags
from ..compute.runtime import ensure_warp, flat_view, run_ranges, warp_scalar, warp_view
from ..compute.simd_lanes import LANES, VECTOR_TYPES, lanes_in, lanes_out


@functools.lru_cache(maxsize=None)
def rotation_function(dtype):
    """A wp.func (w, x, y, z) -> 3x3 rotation matrix of that unit quaternion, for scalar type `dtype`."""
    mat33 = wp.types.matrix((3, 3), dtype)
    one = dtype(1.0)
    two = dtype(2.0)

    @wp.func
    def rotation(w: dtype, x: dtype, y: dtype, z: dtype):
        return mat33(one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
                     two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
                     two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y))

    return rotation


@functools.lru_cache(maxsize=None)
def _covariance_kernel(dtype):
    vec3 = wp.types.vector(3, dtype)
    vec4 = wp.types.vector(4, dtype)
    rotation = rotation_function(dtype)

    @wp.kernel(module="unique")
    def covariance_times_kernel(offset: int, quats: wp.array(dtype=vec4), scales: wp.array(dtype=vec3),
                                vectors: wp.array(dtype=vec3), out: wp.array(dtype=vec3)):
        i = offset + wp.tid()
        q = quats[i] / wp.max(wp.length(quats[i]), dtype(1e-12))
        r = rotation(q[0], q[1], q[2], q[3])
        s = scales[i]
        v = wp.transpose(r) @ vectors[i]
        out[i] = r @ vec3(v[0] * s[0] * s[0], v[1] * s[1] * s[1], v[2] * s[2] * s[2])

    return covariance_times_kernel


# The CPU's float32 version: 16 Gaussians per vector (compute/simd_lanes.py), the same maths (C++ in
# covariance_simd.cpp).
# The product over the lanes (covariance_lanes.h; the CPU's MCMC noise kernel takes it too, strategy/).
COVARIANCE_LANES = read_snippet(__package__, "covariance_lanes.h")
_COVARIANCE_SIMD = read_snippet(__package__, "covariance_simd.cpp", {
    "VECTOR_TYPES": VECTOR_TYPES, "LANES": LANES, "COVARIANCE": COVARIANCE_LANES, "LOAD_Q": lanes_in("q", "quats_", 4),
    "LOAD_S": lanes_in("s", "scales_", 3), "LOAD_V": lanes_in("v", "vectors_", 3),
    "STORE_OUT": lanes_out(["result[0]", "result[1]", "result[2]"], "out_")})

wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512")})
_float_array = wp.array(dtype=wp.float32)


@wp.func_native(_COVARIANCE_SIMD)
def _covariance_chunk(chunk: int, n: int, quats: _float_array, scales: _float_array, vectors: _float_array,
                      out: _float_array): ...


@wp.kernel
def covariance_times_simd(first_chunk: int, n: int, quats: _float_array, scales: _float_array,
                          vectors: _float_array, out: _float_array):
    """One thread per chunk of 16 Gaussians (float32 on the CPU)."""
    _covariance_chunk(first_chunk + wp.tid(), n, quats, scales, vectors, out)


def covariance_times(quats: torch.Tensor, scales: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """Sigma_i @ vectors_i for quaternions [N, 4] (normalised here), activated scales [N, 3], vectors [N, 3]."""
    ensure_warp()
    scalar = warp_scalar(quats.dtype)
    quats, scales, vectors = (t.contiguous() for t in (quats, scales, vectors))  # the kernels read the memory
    out = torch.empty_like(vectors)
    n = quats.shape[0]
    if quats.device.type == "cpu" and quats.dtype == torch.float32:
        views = [flat_view(t) for t in (quats, scales, vectors, out)]
        run_ranges(covariance_times_simd, -(-n // LANES), quats.device, [n, *views], 4096 // LANES)
        return out
    views = [warp_view(t, wp.types.vector(t.shape[1], scalar)) for t in (quats, scales, vectors, out)]
    run_ranges(_covariance_kernel(scalar), n, quats.device, views)
    return out
