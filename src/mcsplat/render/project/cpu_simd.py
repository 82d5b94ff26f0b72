"""SIMD projection and SH colour for the CPU: 16 Gaussians in 16 vector lanes, forward and hand-written backward.

The same maths, conventions and outputs as the Warp kernels of warp_kernel.py (which stay the CUDA path,
the float64 path and the tests' second opinion), written as C++ snippets (`wp.func_native`) over clang vector types
because Warp's kernel language runs one Gaussian per thread and does not vectorise on the CPU. One kernel thread
takes a chunk of 16 consecutive Gaussians: the geometry (camera space, the Jacobian, the 3D and 2D covariances, the
conic, the screen extent, and their chain rule backwards) runs on all 16 at once; the SH colour, whose coefficients
lie in each Gaussian's own row, runs lane by lane over the basis values the vectors computed. The last chunk repeats
its last Gaussian in the spare lanes and stores only its own.

The backward writes every entry of its outputs (zeros for a Gaussian no gradient reaches and for SH bands above the
active degree), so its buffers need no zero-fill first, and it reads the forward's colours for the clamp at 0 instead
of evaluating the SH again: the gradient passes where a colour is above 0 (the Warp kernel also passes it where the
colour before the clamp is exactly 0: the one place the two can differ). Float32 only: warp_kernel.py chooses
these kernels for float32 tensors on the CPU. Each thread writes only its own Gaussians, so the result does not
depend on timing.

Camera numbers come packed in one float32 array (see CAMERA_LAYOUT); the logarithm is a polynomial (a libm call
would stop the lanes from vectorising), relative error about 1e-7, used only for the screen extent, which has margins.

The C++ is in the cpu_simd_*.cpp and .h files beside this module; the host side (outputs, the launches over ranges of
chunks) is at the end of it.
"""

from __future__ import annotations

import torch
import warp as wp

from ...compute.cpp_snippets import read_snippet
from ...compute.cpu_target import kernel_flags
from ...compute.runtime import flat_view, run_ranges
from ...compute.simd_lanes import LANES, SIMD_MATH, VECTOR_TYPES, lanes_in, lanes_out
from ...geometry.sh import SH_C0, SH_C1, SH_C2, SH_C3
from ..constants import TILE_SIZE

# Order of the packed camera numbers: world-to-camera rotation (row-major), translation, camera centre, intrinsics,
# near and far planes, the low-pass filter.
CAMERA_LAYOUT = ("r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22", "t0", "t1", "t2",
                 "centre_x", "centre_y", "centre_z", "fx", "fy", "cx", "cy", "near", "far", "eps2d")


# The C++ is in cpu_simd_*.cpp and .h: the prelude (types, helpers, the camera, the chunk's Gaussians in lanes) and the
# geometry (camera space, the Jacobian, the rotation, the 2D covariance, the SH basis) that forward and backward share.
# The SH constants go in as float literals (the files write {{SH_C1}}f, {{SH_C2_0}}f, ...).
_SH_CONSTANTS = {"SH_C0": SH_C0, "SH_C1": SH_C1, **{f"SH_C2_{k}": value for k, value in enumerate(SH_C2)},
                 **{f"SH_C3_{k}": value for k, value in enumerate(SH_C3)}}
_SH_LITERALS = {name: repr(float(value)) for name, value in _SH_CONSTANTS.items()}


def _load(dst: str, array: str, stride: int) -> str:
    """lanes_in from the kernel's float32 array parameter `array`, read through its data pointer."""
    return lanes_in(dst, f"((const float*){array}.data)", stride)


def _store(values: list[str], array: str, kind: str = "f") -> str:
    """lanes_out into the kernel's array parameter `array` (float32, or int32 for kind "i")."""
    return lanes_out(values, f"(({'int' if kind == 'i' else 'float'}*){array}.data)", kind)


_PRELUDE = read_snippet(__package__, "cpu_simd_prelude.h", {
    "VECTOR_TYPES": VECTOR_TYPES, "SIMD_MATH": SIMD_MATH, "LANES": LANES, "LOAD_MEAN": _load("mean", "means", 3),
    "LOAD_S": _load("s", "scales", 3), "LOAD_Q_RAW": _load("q_raw", "quats", 4)})
_GEOMETRY = read_snippet(__package__, "cpu_simd_geometry.h", _SH_LITERALS)

_FORWARD_BODY = read_snippet(__package__, "cpu_simd_forward.cpp", {
    "PRELUDE": _PRELUDE, "GEOMETRY": _GEOMETRY, "TILE_SIZE": TILE_SIZE,
    "LOAD_OPACITY_ROW": _load("opacity_row", "opacities", 1),
    "STORE_MEANS2D": _store(["mean2d[0]", "mean2d[1]"], "out_means2d"),
    "STORE_CONICS": _store(["conic[0]", "conic[1]", "conic[2]"], "out_conics"),
    "STORE_DEPTHS": _store(["p[2]"], "out_depths"),
    "STORE_COMPENSATIONS": _store(["compensation"], "out_compensations"),
    "STORE_RADII": _store(["kept_radius"], "out_radii", "i"),
    "STORE_TILE_MIN": _store(["kept_lo_x", "kept_lo_y"], "out_tile_min", "i"),
    "STORE_TILE_MAX": _store(["kept_hi_x", "kept_hi_y"], "out_tile_max", "i"),
    "STORE_ALPHA_EXTENT": _store(["box_x", "box_y"], "out_alpha_extent")})



def backward_source(outputs: dict[str, str] | None = None, out_first: str = "0") -> str:
    """The backward's C++ body. `outputs` names a float pointer for each of the gradients' arrays ("means",
    "quats", "scales", "dc", "rest"; default: the kernel's out_* arrays), holding rows from `out_first` on (0: all of
    them; the fused update's scratch rows hold the chunk's alone, from `first`)."""
    pointers = {key: f"(float*)out_{key}.data" for key in ("means", "quats", "scales", "dc", "rest")}
    pointers.update(outputs or {})
    row = f"first - ({out_first})"
    # A lambda called in place (its returns leave the backward alone): a kernel that works on after it (the fused
    # update) then compiles it as this one does, the same fused multiply-adds, the same gradients to the bit.
    return "[&]() {\n" + read_snippet(__package__, "cpu_simd_backward.cpp", {
        "PRELUDE": _PRELUDE, "GEOMETRY": _GEOMETRY, **_SH_LITERALS,
        **{f"OUT_{key.upper()}": pointer for key, pointer in pointers.items()}, "OUT_FIRST": out_first,
        "LOAD_G_MEAN2D": _load("g_mean2d", "grad_means2d", 2), "LOAD_G_CONIC": _load("g_conic", "grad_conics", 3),
        "LOAD_G_COLOR": _load("g_color", "grad_colors", 3),
        "LOAD_G_DEPTH_ROW": _load("g_depth_row", "grad_depths", 1),
        "LOAD_G_COMPENSATION_ROW": _load("g_compensation_row", "grad_compensations", 1),
        "STORE_OUT_MEANS": lanes_out(["kept_mean[0]", "kept_mean[1]", "kept_mean[2]"], "out_means_", row=row),
        "STORE_OUT_SCALES": lanes_out(["kept_scale[0]", "kept_scale[1]", "kept_scale[2]"], "out_scales_", row=row),
        "STORE_OUT_QUATS": lanes_out(["kept_q[0]", "kept_q[1]", "kept_q[2]", "kept_q[3]"], "out_quats_",
                                     row=row)}) + "\n}();\n"


_BACKWARD_BODY = backward_source()


# Same options as the compositing kernels (render/composite/cpu_simd.py): 512-bit vectors where the CPU has them, fused
# multiply-add (`fast`, also across statements: the backward body is a lambda so that the fused update's kernel,
# built with the same options, fuses its copy alike; tests/training/test_fused_projection.py checks the bits).
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512 -ffp-contract=fast")})

_int_array = wp.array(dtype=wp.int32)
_float_array = wp.array(dtype=wp.float32)


@wp.func_native(_FORWARD_BODY)
def _project_chunk(chunk: int, n: int, camera: _float_array, width: int, height: int, tiles_x: int, tiles_y: int,
                   sh_degree: int, opacity_aware_radius: int, antialiased: int,
                   means: _float_array, quats: _float_array, scales: _float_array, opacities: _float_array,
                   sh_dc: _float_array, sh_rest: _float_array, dc_stride: int, rest_stride: int, rest_shift: int,
                   out_means2d: _float_array, out_conics: _float_array, out_depths: _float_array,
                   out_colors: _float_array, out_compensations: _float_array, out_radii: _int_array,
                   out_tile_min: _int_array, out_tile_max: _int_array, out_alpha_extent: _float_array): ...


@wp.func_native(_BACKWARD_BODY)
def _project_chunk_backward(chunk: int, n: int, camera: _float_array, width: int, height: int, sh_degree: int,
                            antialiased: int, means: _float_array, quats: _float_array, scales: _float_array,
                            sh_dc: _float_array, sh_rest: _float_array, dc_stride: int, rest_stride: int,
                            rest_shift: int, rest_count: int, colors: _float_array, grad_means2d: _float_array,
                            grad_conics: _float_array, grad_depths: _float_array, grad_colors: _float_array,
                            grad_compensations: _float_array, out_means: _float_array, out_quats: _float_array,
                            out_scales: _float_array, out_dc: _float_array, out_rest: _float_array, view_grad: int,
                            out_view: _float_array): ...


@wp.kernel
def project_simd(first_chunk: int, n: int, camera: _float_array, width: int, height: int, tiles_x: int,
                 tiles_y: int, sh_degree: int, opacity_aware_radius: int, antialiased: int,
                 means: _float_array, quats: _float_array, scales: _float_array, opacities: _float_array,
                 sh_dc: _float_array, sh_rest: _float_array, dc_stride: int, rest_stride: int, rest_shift: int,
                 out_means2d: _float_array, out_conics: _float_array, out_depths: _float_array,
                 out_colors: _float_array, out_compensations: _float_array, out_radii: _int_array,
                 out_tile_min: _int_array, out_tile_max: _int_array, out_alpha_extent: _float_array):
    """One thread per chunk of 16 Gaussians, from chunk `first_chunk` on."""
    _project_chunk(first_chunk + wp.tid(), n, camera, width, height, tiles_x, tiles_y, sh_degree,
                   opacity_aware_radius, antialiased, means, quats, scales, opacities, sh_dc, sh_rest, dc_stride,
                   rest_stride, rest_shift, out_means2d, out_conics, out_depths, out_colors, out_compensations,
                   out_radii, out_tile_min, out_tile_max, out_alpha_extent)


@wp.kernel
def project_backward_simd(first_chunk: int, n: int, camera: _float_array, width: int, height: int, sh_degree: int,
                          antialiased: int, means: _float_array, quats: _float_array, scales: _float_array,
                          sh_dc: _float_array, sh_rest: _float_array, dc_stride: int, rest_stride: int,
                          rest_shift: int, rest_count: int, colors: _float_array, grad_means2d: _float_array,
                          grad_conics: _float_array, grad_depths: _float_array, grad_colors: _float_array,
                          grad_compensations: _float_array, out_means: _float_array, out_quats: _float_array,
                          out_scales: _float_array, out_dc: _float_array, out_rest: _float_array, view_grad: int,
                          out_view: _float_array):
    """One thread per chunk of 16 Gaussians; every entry of the outputs is written."""
    _project_chunk_backward(first_chunk + wp.tid(), n, camera, width, height, sh_degree, antialiased, means, quats,
                            scales, sh_dc, sh_rest, dc_stride, rest_stride, rest_shift, rest_count, colors,
                            grad_means2d,
                            grad_conics, grad_depths, grad_colors, grad_compensations, out_means, out_quats,
                            out_scales, out_dc, out_rest, view_grad, out_view)


# The host side: one Warp thread per chunk of LANES Gaussians over ranges of chunks.

_flat = flat_view  # the kernels take every array as a flat run of elements


def _sh_layout(sh_dc: torch.Tensor, sh_rest: torch.Tensor, together: bool) -> list[int]:
    """(dc row stride, rest row stride, rest shift, rest count) in floats and coefficients: with `together`, sh_dc
    is sh_rest and holds every band [N, K, 3]; otherwise the DC band [N, 1, 3] and the rest [N, K - 1, 3]."""
    if together:
        k = sh_dc.shape[1]
        return [3 * k, 3 * k, 1, k - 1]
    return [3, 3 * sh_rest.shape[1], 0, sh_rest.shape[1]]


def _chunks(n: int) -> int:
    return -(-n // LANES)


def project(means, quats, scales, opacities, sh_dc, sh_rest, together: bool, camera: torch.Tensor, width: int,
            height: int, tiles_x: int, tiles_y: int, sh_degree: int, opacity_aware_radius: bool, antialiased: bool):
    """-> means2d [N, 2], conics [N, 3], depths [N], colours [N, 3], compensations [N] (1 unless antialiased), radii
    [N] int32, tile_min and tile_max [N, 2] int32, alpha_extent [N, 2]. `camera`: float32 numbers in
    project.CAMERA_LAYOUT's order. Inputs contiguous float32 on the CPU."""
    n = means.shape[0]
    outputs = [torch.empty(n, 2), torch.empty(n, 3), torch.empty(n), torch.empty(n, 3), torch.empty(n),
               torch.empty(n, dtype=torch.int32), torch.empty(n, 2, dtype=torch.int32),
               torch.empty(n, 2, dtype=torch.int32), torch.empty(n, 2)]
    dc_stride, rest_stride, rest_shift, _ = _sh_layout(sh_dc, sh_rest, together)
    run_ranges(project_simd, _chunks(n), means.device, [
        n, _flat(camera), width, height, tiles_x, tiles_y, sh_degree, int(opacity_aware_radius), int(antialiased),
        *(_flat(t) for t in (means, quats, scales, opacities, sh_dc, sh_rest)), dc_stride, rest_stride, rest_shift,
        *(_flat(t) for t in outputs)], min_per_thread=4096 // LANES)
    return outputs


def project_backward(means, quats, scales, sh_dc, sh_rest, together: bool, camera: torch.Tensor, width: int,
                     height: int, sh_degree: int, antialiased: bool, colors: torch.Tensor, upstream: list[torch.Tensor],
                     view_grad: bool):
    """Gradients for (means, quats, scales, sh_dc, sh_rest) from the upstream gradients of (means2d, conics, depths,
    colours, compensations), and with `view_grad` each Gaussian's share of the view matrix's [N, 12] (rotation
    row-major, translation), else None. `colors`: the forward's (the clamp at 0 passes no gradient where they are
    0). With `together` the SH gradient is one tensor, returned twice."""
    n = means.shape[0]
    grads = [torch.empty_like(t) for t in (means, quats, scales, sh_dc)]
    grads.append(grads[3] if together else torch.empty_like(sh_rest))
    per_gaussian_view = torch.empty(n if view_grad else 1, 12)
    run_ranges(project_backward_simd, _chunks(n), means.device, [
        n, _flat(camera), width, height, sh_degree, int(antialiased),
        *(_flat(t) for t in (means, quats, scales, sh_dc, sh_rest)), *_sh_layout(sh_dc, sh_rest, together),
        _flat(colors), *(_flat(t) for t in upstream), *(_flat(t) for t in grads), int(view_grad),
        _flat(per_gaussian_view)],
        min_per_thread=4096 // LANES)
    return grads, per_gaussian_view if view_grad else None
