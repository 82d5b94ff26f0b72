"""EWA projection and SH colour of every Gaussian in one kernel, with its backward: a Warp kernel (CUDA, float64, and
the CPU's second opinion) defined here, or for float32 on the CPU the SIMD kernels of cpu_simd.py (16 Gaussians
per vector, several times faster than this kernel there: "The pieces alone" in
benchmarks/results/train_speed/2026-11-27-kernels-side-by-side.md), chosen as kernel_choice.py says.

Same maths and conventions as torch_autograd.py (which stays as the readable torch version and the benchmarks'
baseline): OpenCV camera, pixel centres at +0.5, the 3DGS low-pass filter (+eps2d on the 2D covariance diagonal;
antialiased, with Mip-Splatting's opacity compensation as an output), the Jacobian's view direction clamped to 1.3x the
field of view, SH colour + 0.5 clamped at 0. One thread per Gaussian; the kernel is straight-line code; the backward
kernel recomputes it and applies the chain rule by hand (Warp's generated adjoint is correct here but far slower than
the forward on the CPU: docs/measurements-log.md, "CPU kernels (rasterizer.py, train_speed.py), 2026-11-22"), and on
request each Gaussian's share of the view matrix's gradient (pose refinement). The tests hold both against the torch
version, the dense reference renderer and torch's gradcheck in float64. On the CPU, ranges of Gaussians run from the
rasterizer's thread pool; each thread writes only its own Gaussians, so the result does not depend on timing.
tests/render/test_project_simd.py holds the SIMD kernels to the float64 truth as closely as this kernel in float32.
Both read the camera as an array on the device (packed_camera, made once per camera), so that a launch's arguments do
not change from view to view (what a CUDA graph replays).

(No `from __future__ import annotations` here: Warp reads the kernels' annotations as live objects.)
"""

import functools

import torch
import warp as wp

from ...camera import Camera
from ...compute.runtime import ensure_warp, run_ranges, warp_scalar, warp_view
from ...geometry.covariance import rotation_function
from ...geometry.sh import SH_C0, SH_C1, SH_C2, SH_C3
from ..constants import FAR_PLANE, LOW_PASS, NEAR_PLANE, TILE_SIZE
from . import camera_slot, cpu_simd as simd, deferred
from .cpu_simd import CAMERA_LAYOUT
from ..kernel_choice import kernels_for
from .torch_autograd import Projection

# Warp kernels read module constants only as plain numbers.
SH_C2_0, SH_C2_1, SH_C2_2, SH_C2_3, SH_C2_4 = SH_C2
SH_C3_0, SH_C3_1, SH_C3_2, SH_C3_3, SH_C3_4, SH_C3_5, SH_C3_6 = SH_C3


@functools.lru_cache(maxsize=None)
def projection_kernels(dtype):
    """(forward, backward) projection kernels for scalar type wp.float32 or wp.float64."""
    vec2 = wp.types.vector(2, dtype)
    vec3 = wp.types.vector(3, dtype)
    vec4 = wp.types.vector(4, dtype)
    vec16 = wp.types.vector(16, dtype)
    mat22 = wp.types.matrix((2, 2), dtype)
    mat23 = wp.types.matrix((2, 3), dtype)
    mat33 = wp.types.matrix((3, 3), dtype)
    zero = dtype(0.0)
    one = dtype(1.0)
    two = dtype(2.0)
    quat_rotation = rotation_function(dtype)

    @wp.func
    def camera_of(camera: wp.array(dtype=dtype)):
        """The packed camera (cpu_simd.CAMERA_LAYOUT's order): rotation, translation, centre, fx, fy, cx, cy, near,
        far, eps2d. From a device array, so that a launch's arguments do not change with the view."""
        rotation = mat33(camera[0], camera[1], camera[2], camera[3], camera[4], camera[5], camera[6], camera[7],
                         camera[8])
        return (rotation, vec3(camera[9], camera[10], camera[11]), vec3(camera[12], camera[13], camera[14]),
                camera[15], camera[16], camera[17], camera[18], camera[19], camera[20], camera[21])

    @wp.func
    def view_limits(fx: dtype, fy: dtype, cx: dtype, cy: dtype, width: int, height: int):
        """Bounds of x/z and y/z for the Jacobian: the field of view widened by 30% on each side (3DGS, gsplat)."""
        tan_fovx = dtype(0.5) * dtype(width) / fx
        tan_fovy = dtype(0.5) * dtype(height) / fy
        return (cx / fx + dtype(0.3) * tan_fovx, (dtype(width) - cx) / fx + dtype(0.3) * tan_fovx,
                cy / fy + dtype(0.3) * tan_fovy, (dtype(height) - cy) / fy + dtype(0.3) * tan_fovy)

    @wp.func
    def camera_point(rotation: mat33, translation: vec3, mean: vec3, near: dtype, far: dtype):
        """(p, in range, safe depth): the camera-space position, whether its depth is within the planes, and that
        depth or 1. Culled Gaussians still flow through the maths: the safe depth keeps their (unused) gradients
        finite."""
        p = rotation @ mean + translation
        in_range = p[2] > near and p[2] < far
        return p, in_range, wp.where(in_range, p[2], one)

    @wp.func
    def scaled_rotation(q_raw: vec4, scale: vec3):
        """(|q| clamped at 1e-12, unit q, R(q), M = R(q) diag(s)): the 3D covariance is M M^T."""
        q_norm = wp.max(wp.length(q_raw), dtype(1e-12))
        q = q_raw / q_norm
        rot = quat_rotation(q[0], q[1], q[2], q[3])
        return q_norm, q, rot, rot @ wp.diag(scale)

    @wp.func
    def screen_covariance(rotation: mat33, m: mat33, jacobian: mat23, eps2d: dtype, in_range: bool):
        """(V = W M M^T W^T, cov2d = J V J^T, a, b, c, valid, det_safe): the 2D covariance (a, b; b, c) with the
        low-pass on its diagonal, whether its conic is valid, and its determinant or 1."""
        cov_cam = rotation @ (m @ wp.transpose(m)) @ wp.transpose(rotation)
        cov2d = jacobian @ cov_cam @ wp.transpose(jacobian)
        a = cov2d[0, 0] + eps2d
        b = cov2d[0, 1]
        c = cov2d[1, 1] + eps2d
        det = a * c - b * b
        valid = in_range and det > zero
        return cov_cam, cov2d, a, b, c, valid, wp.where(valid, det, one)

    @wp.func
    def sh_color(sh_dc: wp.array2d(dtype=vec3), sh_rest: wp.array2d(dtype=vec3), shift: int, i: int,
                 sh_degree: int, d: vec3):
        """SH colour (before + 0.5 and the clamp) along the unit direction d; sh_rest[i, shift + k - 1] is the
        coefficient of basis function k (shift 0 when sh_rest holds bands 1-3 alone, 1 when it holds all)."""
        x = d[0]
        y = d[1]
        z = d[2]
        color = dtype(SH_C0) * sh_dc[i, 0]
        if sh_degree >= 1:
            color = color + dtype(SH_C1) * (-y * sh_rest[i, shift] + z * sh_rest[i, shift + 1]
                                             - x * sh_rest[i, shift + 2])
        if sh_degree >= 2:
            xx = x * x
            yy = y * y
            zz = z * z
            color = color + (dtype(SH_C2_0) * x * y * sh_rest[i, shift + 3]
                             + dtype(SH_C2_1) * y * z * sh_rest[i, shift + 4]
                             + dtype(SH_C2_2) * (two * zz - xx - yy) * sh_rest[i, shift + 5]
                             + dtype(SH_C2_3) * x * z * sh_rest[i, shift + 6]
                             + dtype(SH_C2_4) * (xx - yy) * sh_rest[i, shift + 7])
            if sh_degree >= 3:
                color = color + (dtype(SH_C3_0) * y * (dtype(3.0) * xx - yy) * sh_rest[i, shift + 8]
                                 + dtype(SH_C3_1) * x * y * z * sh_rest[i, shift + 9]
                                 + dtype(SH_C3_2) * y * (dtype(4.0) * zz - xx - yy) * sh_rest[i, shift + 10]
                                 + dtype(SH_C3_3) * z * (two * zz - dtype(3.0) * (xx + yy)) * sh_rest[i, shift + 11]
                                 + dtype(SH_C3_4) * x * (dtype(4.0) * zz - xx - yy) * sh_rest[i, shift + 12]
                                 + dtype(SH_C3_5) * z * (xx - yy) * sh_rest[i, shift + 13]
                                 + dtype(SH_C3_6) * x * (xx - dtype(3.0) * yy) * sh_rest[i, shift + 14])
        return color

    @wp.kernel(module="unique")
    def project(
        offset: int, camera: wp.array(dtype=dtype), width: int, height: int, tiles_x: int, tiles_y: int,
        sh_degree: int, opacity_aware_radius: int, antialiased: int,
        means: wp.array(dtype=vec3), quats: wp.array(dtype=vec4), scales: wp.array(dtype=vec3),
        opacities: wp.array(dtype=dtype), sh_dc: wp.array2d(dtype=vec3), sh_rest: wp.array2d(dtype=vec3),
        rest_shift: int,  # sh_rest[i, rest_shift + k - 1] is band coefficient k: 0 for the rest alone, 1 for all
        means2d: wp.array(dtype=vec2), conics: wp.array(dtype=vec3), depths: wp.array(dtype=dtype),
        colors: wp.array(dtype=vec3), compensations: wp.array(dtype=dtype),
        radii: wp.array(dtype=wp.int32), tile_min: wp.array2d(dtype=wp.int32), tile_max: wp.array2d(dtype=wp.int32),
        alpha_extent: wp.array(dtype=vec2),
    ):
        i = offset + wp.tid()
        rotation, translation, camera_center, fx, fy, cx, cy, near, far, eps2d = camera_of(camera)
        mean = means[i]
        p, in_range, z_safe = camera_point(rotation, translation, mean, near, far)
        lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos = view_limits(fx, fy, cx, cy, width, height)
        tx = z_safe * wp.clamp(p[0] / z_safe, -lim_x_neg, lim_x_pos)
        ty = z_safe * wp.clamp(p[1] / z_safe, -lim_y_neg, lim_y_pos)
        jacobian = mat23(fx / z_safe, zero, -fx * tx / (z_safe * z_safe),
                         zero, fy / z_safe, -fy * ty / (z_safe * z_safe))

        _q_norm, _q, _rot, m = scaled_rotation(quats[i], scales[i])
        _cov_cam, cov2d, a, b, c, valid, det_safe = screen_covariance(rotation, m, jacobian, eps2d, in_range)
        conics[i] = vec3(c / det_safe, -b / det_safe, a / det_safe)
        if antialiased != 0:
            # Mip-Splatting's 2D filter: the low-pass widens the splat, so its opacity shrinks by the ratio of the
            # areas (sqrt of the determinants before and after) and a sub-pixel splat no longer paints a whole pixel.
            det_unfiltered = cov2d[0, 0] * cov2d[1, 1] - b * b
            compensations[i] = wp.sqrt(wp.max(det_unfiltered / det_safe, zero))
        else:
            compensations[i] = one
        mean2d = vec2(fx * p[0] / z_safe + cx, fy * p[1] / z_safe + cy)
        means2d[i] = mean2d
        depths[i] = p[2]

        # View-dependent colour along the camera-to-Gaussian direction (3DGS's SH order and signs).
        d = wp.normalize(mean - camera_center)
        color = sh_color(sh_dc, sh_rest, rest_shift, i, sh_degree, d)
        colors[i] = vec3(wp.max(color[0] + dtype(0.5), zero), wp.max(color[1] + dtype(0.5), zero),
                         wp.max(color[2] + dtype(0.5), zero))

        # Screen extent (no gradient): radius from the largest eigenvalue, the tiles it touches, the alpha box.
        opacity = opacities[i]
        mid = dtype(0.5) * (a + c)
        lambda_max = mid + wp.sqrt(wp.max(dtype(0.25) * (a - c) * (a - c) + b * b, dtype(0.1)))
        extent = dtype(3.0)
        if opacity_aware_radius != 0:
            # Beyond sqrt(2 ln(255 o)) sigma the alpha falls under 1/255 and the pixel is skipped anyway.
            extent = wp.min(wp.sqrt(wp.max(two * wp.log(wp.max(dtype(255.0) * opacity, one)), zero)), dtype(3.0))
            valid = valid and dtype(255.0) * opacity > one
        radius = wp.ceil(extent * wp.sqrt(wp.max(lambda_max, zero)))
        lo_x = wp.min(wp.max(wp.floor((mean2d[0] - radius) / dtype(TILE_SIZE)), zero), dtype(tiles_x))
        lo_y = wp.min(wp.max(wp.floor((mean2d[1] - radius) / dtype(TILE_SIZE)), zero), dtype(tiles_y))
        hi_x = wp.min(wp.max(wp.floor((mean2d[0] + radius) / dtype(TILE_SIZE)) + one, zero), dtype(tiles_x))
        hi_y = wp.min(wp.max(wp.floor((mean2d[1] + radius) / dtype(TILE_SIZE)) + one, zero), dtype(tiles_y))
        finite = wp.isfinite(mean2d[0]) and wp.isfinite(mean2d[1])
        valid = valid and radius > zero and hi_x > lo_x and hi_y > lo_y and finite
        if valid:
            radii[i] = int(radius)
            tile_min[i, 0] = int(lo_x)
            tile_min[i, 1] = int(lo_y)
            tile_max[i, 0] = int(hi_x)
            tile_max[i, 1] = int(hi_y)
        else:
            radii[i] = 0
            tile_min[i, 0] = 0
            tile_min[i, 1] = 0
            tile_max[i, 0] = 0
            tile_max[i, 1] = 0
        # Half-widths of the box outside which o exp(-d^T Q d / 2) < 1/255 (see project._alpha_extent).
        k = wp.max(two * wp.log(wp.max(dtype(255.0) * opacity, dtype(1e-30))), zero)
        if k > zero:
            alpha_extent[i] = vec2(wp.sqrt(k * wp.max(a, zero)) * dtype(1.001) + dtype(0.01),
                                   wp.sqrt(k * wp.max(c, zero)) * dtype(1.001) + dtype(0.01))
        else:
            alpha_extent[i] = vec2(zero, zero)

    @wp.func
    def backward_of_gaussian(
        i: int, rotation: mat33, translation: vec3, camera_center: vec3,
        fx: dtype, fy: dtype, cx: dtype, cy: dtype, width: int, height: int, near: dtype, far: dtype,
        eps2d: dtype, sh_degree: int, antialiased: int,
        means: wp.array(dtype=vec3), quats: wp.array(dtype=vec4), scales: wp.array(dtype=vec3),
        sh_dc: wp.array2d(dtype=vec3), sh_rest: wp.array2d(dtype=vec3), rest_shift: int,
        grad_means2d: wp.array(dtype=vec2), grad_conics: wp.array(dtype=vec3), grad_depths: wp.array(dtype=dtype),
        grad_colors: wp.array(dtype=vec3), grad_compensations: wp.array(dtype=dtype),
        out_means: wp.array(dtype=vec3), out_quats: wp.array(dtype=vec4), out_scales: wp.array(dtype=vec3),
        out_dc: wp.array2d(dtype=vec3), out_rest: wp.array2d(dtype=vec3),
        view_grad: int, out_view: wp.array2d(dtype=dtype),
    ):
        """Recomputes the forward and applies the chain rule by hand, step by step in reverse. With `view_grad`,
        also this Gaussian's share of the gradient of the world-to-camera rotation W (row-major, out_view[i, 0:9])
        and translation t (out_view[i, 9:12]), which the caller sums (pose refinement). Gaussian i's rows of the
        outputs are written where some gradient reaches it, and its SH rows up to `sh_degree` only: the caller
        zeroes them first."""
        g_mean2d = grad_means2d[i]
        g_conic = grad_conics[i]
        g_depth = grad_depths[i]
        g_color = grad_colors[i]
        g_compensation = zero
        if antialiased != 0:
            g_compensation = grad_compensations[i]
        if (g_mean2d[0] == zero and g_mean2d[1] == zero and g_conic[0] == zero and g_conic[1] == zero
                and g_conic[2] == zero and g_depth == zero and g_color[0] == zero and g_color[1] == zero
                and g_color[2] == zero and g_compensation == zero):
            return  # no gradient reaches this Gaussian (culled, or outside every pixel's list)

        # ---- forward, again
        mean = means[i]
        p, in_range, z_safe = camera_point(rotation, translation, mean, near, far)
        lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos = view_limits(fx, fy, cx, cy, width, height)
        u = p[0] / z_safe
        v = p[1] / z_safe
        u_clamped = wp.clamp(u, -lim_x_neg, lim_x_pos)
        v_clamped = wp.clamp(v, -lim_y_neg, lim_y_pos)
        tx = z_safe * u_clamped
        ty = z_safe * v_clamped
        z2 = z_safe * z_safe
        jacobian = mat23(fx / z_safe, zero, -fx * tx / z2, zero, fy / z_safe, -fy * ty / z2)
        q_raw = quats[i]
        scale = scales[i]
        q_norm, q, rot, m = scaled_rotation(q_raw, scale)
        cov_cam, _cov2d, a, b, c, valid, det_safe = screen_covariance(rotation, m, jacobian, eps2d, in_range)

        # ---- conic = (c, -b, a) / det
        g_det = -(g_conic[0] * c - g_conic[1] * b + g_conic[2] * a) / (det_safe * det_safe)
        g_a = g_conic[2] / det_safe
        g_b = -g_conic[1] / det_safe
        g_c = g_conic[0] / det_safe
        if valid:
            g_a = g_a + g_det * c
            g_b = g_b - two * g_det * b
            g_c = g_c + g_det * a
            # ---- compensation = sqrt(ratio), ratio = det((a, b; b, c) - eps2d I) / det
            ratio = ((a - eps2d) * (c - eps2d) - b * b) / det_safe
            if g_compensation != zero and ratio > zero:
                g_ratio = g_compensation / (two * wp.sqrt(ratio))
                g_a = g_a + g_ratio * ((c - eps2d) - ratio * c) / det_safe
                g_b = g_b - g_ratio * two * b * (one - ratio) / det_safe
                g_c = g_c + g_ratio * ((a - eps2d) - ratio * a) / det_safe
        g_cov2d = mat22(g_a, g_b, zero, g_c)  # the forward reads cov2d[0, 1] only
        # ---- cov2d = J V J^T, V = W Sigma W^T, Sigma = M M^T, M = R(q) diag(s)
        g_jacobian = (g_cov2d + wp.transpose(g_cov2d)) @ jacobian @ cov_cam
        g_cov_cam = wp.transpose(jacobian) @ g_cov2d @ jacobian
        g_sigma = wp.transpose(rotation) @ g_cov_cam @ rotation
        g_m = (g_sigma + wp.transpose(g_sigma)) @ m
        g_scale = vec3(zero, zero, zero)
        g_rot = mat33()
        for r in range(3):
            for col in range(3):
                g_rot[r, col] = g_m[r, col] * scale[col]
                g_scale[col] = g_scale[col] + g_m[r, col] * rot[r, col]
        out_scales[i] = g_scale
        w = q[0]
        x = q[1]
        y = q[2]
        qz = q[3]
        g_q = two * vec4(
            -qz * g_rot[0, 1] + y * g_rot[0, 2] + qz * g_rot[1, 0] - x * g_rot[1, 2] - y * g_rot[2, 0]
            + x * g_rot[2, 1],
            y * g_rot[0, 1] + qz * g_rot[0, 2] + y * g_rot[1, 0] - two * x * g_rot[1, 1] - w * g_rot[1, 2]
            + qz * g_rot[2, 0] + w * g_rot[2, 1] - two * x * g_rot[2, 2],
            -two * y * g_rot[0, 0] + x * g_rot[0, 1] + w * g_rot[0, 2] + x * g_rot[1, 0] + qz * g_rot[1, 2]
            - w * g_rot[2, 0] + qz * g_rot[2, 1] - two * y * g_rot[2, 2],
            -two * qz * g_rot[0, 0] - w * g_rot[0, 1] + x * g_rot[0, 2] + w * g_rot[1, 0] - two * qz * g_rot[1, 1]
            + y * g_rot[1, 2] + x * g_rot[2, 0] + y * g_rot[2, 1])
        if wp.length(q_raw) >= dtype(1e-12):
            g_q = (g_q - q * wp.dot(q, g_q)) / q_norm
        else:
            g_q = g_q / q_norm  # under the clamp the norm is a constant
        out_quats[i] = g_q

        # ---- the Jacobian's dependence on the camera-space position
        g_z_safe = (-fx * g_jacobian[0, 0] - fy * g_jacobian[1, 1]) / z2 \
            + two * (fx * tx * g_jacobian[0, 2] + fy * ty * g_jacobian[1, 2]) / (z2 * z_safe)
        g_tx = -fx * g_jacobian[0, 2] / z2
        g_ty = -fy * g_jacobian[1, 2] / z2
        g_p = vec3(zero, zero, zero)
        if u >= -lim_x_neg and u <= lim_x_pos:
            g_p[0] = g_p[0] + g_tx
        else:
            g_z_safe = g_z_safe + g_tx * u_clamped
        if v >= -lim_y_neg and v <= lim_y_pos:
            g_p[1] = g_p[1] + g_ty
        else:
            g_z_safe = g_z_safe + g_ty * v_clamped
        # ---- means2d = (fx x / z + cx, fy y / z + cy), depth = z
        g_p[0] = g_p[0] + g_mean2d[0] * fx / z_safe
        g_p[1] = g_p[1] + g_mean2d[1] * fy / z_safe
        g_z_safe = g_z_safe - (g_mean2d[0] * fx * p[0] + g_mean2d[1] * fy * p[1]) / z2
        g_p[2] = g_p[2] + g_depth
        if in_range:
            g_p[2] = g_p[2] + g_z_safe
        g_mean = wp.transpose(rotation) @ g_p

        # ---- colour = max(SH(d) + 0.5, 0), d = normalize(mean - camera centre)
        offset_dir = mean - camera_center
        d = wp.normalize(offset_dir)
        color = sh_color(sh_dc, sh_rest, rest_shift, i, sh_degree, d)
        dx = d[0]
        dy = d[1]
        dz = d[2]
        xx = dx * dx
        yy = dy * dy
        zz = dz * dz
        g = vec3(wp.where(color[0] + dtype(0.5) >= zero, g_color[0], zero),
                 wp.where(color[1] + dtype(0.5) >= zero, g_color[1], zero),
                 wp.where(color[2] + dtype(0.5) >= zero, g_color[2], zero))
        out_dc[i, 0] = dtype(SH_C0) * g
        s = vec16()  # s[k] = g . (coefficient of basis function k), for the bands up to sh_degree
        for k in range(1, (sh_degree + 1) * (sh_degree + 1)):
            s[k] = wp.dot(g, sh_rest[i, rest_shift + k - 1])
        g_d = vec3(zero, zero, zero)
        if sh_degree >= 1:
            out_rest[i, rest_shift] = -dtype(SH_C1) * dy * g
            out_rest[i, rest_shift + 1] = dtype(SH_C1) * dz * g
            out_rest[i, rest_shift + 2] = -dtype(SH_C1) * dx * g
            g_d = dtype(SH_C1) * vec3(-s[3], -s[1], s[2])
        if sh_degree >= 2:
            out_rest[i, rest_shift + 3] = dtype(SH_C2_0) * dx * dy * g
            out_rest[i, rest_shift + 4] = dtype(SH_C2_1) * dy * dz * g
            out_rest[i, rest_shift + 5] = dtype(SH_C2_2) * (two * zz - xx - yy) * g
            out_rest[i, rest_shift + 6] = dtype(SH_C2_3) * dx * dz * g
            out_rest[i, rest_shift + 7] = dtype(SH_C2_4) * (xx - yy) * g
            g_d = g_d + vec3(
                dtype(SH_C2_0) * dy * s[4] - two * dtype(SH_C2_2) * dx * s[6] + dtype(SH_C2_3) * dz * s[7]
                + two * dtype(SH_C2_4) * dx * s[8],
                dtype(SH_C2_0) * dx * s[4] + dtype(SH_C2_1) * dz * s[5] - two * dtype(SH_C2_2) * dy * s[6]
                - two * dtype(SH_C2_4) * dy * s[8],
                dtype(SH_C2_1) * dy * s[5] + dtype(4.0) * dtype(SH_C2_2) * dz * s[6] + dtype(SH_C2_3) * dx * s[7])
        if sh_degree >= 3:
            out_rest[i, rest_shift + 8] = dtype(SH_C3_0) * dy * (dtype(3.0) * xx - yy) * g
            out_rest[i, rest_shift + 9] = dtype(SH_C3_1) * dx * dy * dz * g
            out_rest[i, rest_shift + 10] = dtype(SH_C3_2) * dy * (dtype(4.0) * zz - xx - yy) * g
            out_rest[i, rest_shift + 11] = dtype(SH_C3_3) * dz * (two * zz - dtype(3.0) * xx - dtype(3.0) * yy) * g
            out_rest[i, rest_shift + 12] = dtype(SH_C3_4) * dx * (dtype(4.0) * zz - xx - yy) * g
            out_rest[i, rest_shift + 13] = dtype(SH_C3_5) * dz * (xx - yy) * g
            out_rest[i, rest_shift + 14] = dtype(SH_C3_6) * dx * (xx - dtype(3.0) * yy) * g
            g_d = g_d + vec3(
                dtype(SH_C3_0) * dtype(6.0) * dx * dy * s[9] + dtype(SH_C3_1) * dy * dz * s[10]
                - dtype(SH_C3_2) * two * dx * dy * s[11] - dtype(SH_C3_3) * dtype(6.0) * dx * dz * s[12]
                + dtype(SH_C3_4) * (dtype(4.0) * zz - dtype(3.0) * xx - yy) * s[13]
                + dtype(SH_C3_5) * two * dx * dz * s[14] + dtype(SH_C3_6) * dtype(3.0) * (xx - yy) * s[15],
                dtype(SH_C3_0) * dtype(3.0) * (xx - yy) * s[9] + dtype(SH_C3_1) * dx * dz * s[10]
                + dtype(SH_C3_2) * (dtype(4.0) * zz - xx - dtype(3.0) * yy) * s[11]
                - dtype(SH_C3_3) * dtype(6.0) * dy * dz * s[12] - dtype(SH_C3_4) * two * dx * dy * s[13]
                - dtype(SH_C3_5) * two * dy * dz * s[14] - dtype(SH_C3_6) * dtype(6.0) * dx * dy * s[15],
                dtype(SH_C3_1) * dx * dy * s[10] + dtype(SH_C3_2) * dtype(8.0) * dy * dz * s[11]
                + dtype(SH_C3_3) * (dtype(6.0) * zz - dtype(3.0) * xx - dtype(3.0) * yy) * s[12]
                + dtype(SH_C3_4) * dtype(8.0) * dx * dz * s[13] + dtype(SH_C3_5) * (xx - yy) * s[14])
        length = wp.length(offset_dir)
        g_offset = vec3(zero, zero, zero)  # of mean - camera centre
        if length > zero:
            g_offset = (g_d - d * wp.dot(d, g_d)) / length
        out_means[i] = g_mean + g_offset

        if view_grad != 0:
            # p = W mean + t; V = W Sigma W^T; camera centre = -W^T t (the colour's view direction).
            g_w = wp.outer(g_p, mean) + (g_cov_cam + wp.transpose(g_cov_cam)) @ rotation @ (m @ wp.transpose(m)) \
                + wp.outer(translation, g_offset)
            g_t = g_p + rotation @ g_offset
            for r in range(3):
                for col in range(3):
                    out_view[i, 3 * r + col] = g_w[r, col]
                out_view[i, 9 + r] = g_t[r]

    @wp.kernel(module="unique")
    def project_backward(
        offset: int, camera: wp.array(dtype=dtype), width: int, height: int, sh_degree: int, antialiased: int,
        means: wp.array(dtype=vec3), quats: wp.array(dtype=vec4), scales: wp.array(dtype=vec3),
        sh_dc: wp.array2d(dtype=vec3), sh_rest: wp.array2d(dtype=vec3), rest_shift: int,
        grad_means2d: wp.array(dtype=vec2), grad_conics: wp.array(dtype=vec3), grad_depths: wp.array(dtype=dtype),
        grad_colors: wp.array(dtype=vec3), grad_compensations: wp.array(dtype=dtype),
        out_means: wp.array(dtype=vec3), out_quats: wp.array(dtype=vec4), out_scales: wp.array(dtype=vec3),
        out_dc: wp.array2d(dtype=vec3), out_rest: wp.array2d(dtype=vec3),
        view_grad: int, out_view: wp.array2d(dtype=dtype),
    ):
        """backward_of_gaussian for Gaussians offset + tid (the outputs zeroed by the caller)."""
        rotation, translation, camera_center, fx, fy, cx, cy, near, far, eps2d = camera_of(camera)
        backward_of_gaussian(
            offset + wp.tid(), rotation, translation, camera_center, fx, fy, cx, cy, width, height, near, far, eps2d,
            sh_degree, antialiased, means, quats, scales, sh_dc, sh_rest, rest_shift, grad_means2d, grad_conics,
            grad_depths, grad_colors, grad_compensations, out_means, out_quats, out_scales, out_dc, out_rest,
            view_grad, out_view)

    project_backward.of_gaussian = backward_of_gaussian  # the fused update's kernel calls it (optim/fused_projection)
    project_backward.camera_of = camera_of
    return project, project_backward


def _vector_view(tensor: torch.Tensor, length: int, dtype):
    return warp_view(tensor, wp.types.vector(length, dtype))


def _scalar_view(tensor: torch.Tensor):
    return warp_view(tensor)


class _ProjectFunction(torch.autograd.Function):
    """(means, quats, scales, sh_dc, sh_rest) -> (means2d, conics, depths, colors, compensations); radii, tile
    rectangles and alpha extents come along without gradient (opacities enter only those). Compensations are 1 unless
    `antialiased`. `world_to_camera`, the camera's 4x4 view matrix, is an input only for its gradient (pose
    refinement; None otherwise): the kernels read the view from `camera_args`. The SH coefficients come as the DC band
    [N, 1, 3] and the rest [N, K - 1, 3] (GaussianModel keeps them apart: no concatenation per render), or, with
    sh_rest None, all together in sh_dc [N, K, 3]."""

    @staticmethod
    def forward(ctx, means, quats, scales, sh_dc, sh_rest, opacities, camera_args: tuple, sh_degree: int,
                opacity_aware_radius: bool, antialiased: bool, world_to_camera: torch.Tensor | None,
                deferral: deferred.Deferral | None):
        ensure_warp()
        ctx.set_materialize_grads(False)  # the backward takes None (no zeros made for the outputs without gradient)
        ctx.together = sh_rest is None
        # No detach (an operator each): the forward runs without grad mode and saves its inputs as they came.
        means, quats, scales, sh_dc, opacities = (t.contiguous() for t in (means, quats, scales, sh_dc, opacities))
        sh_rest = sh_dc if ctx.together else sh_rest.contiguous()
        ctx.simd = kernels_for(means) == "simd"
        ctx.packed_camera = packed_camera(camera_args, means.dtype, means.device)
        if ctx.simd:
            outputs = simd.project(means, quats, scales, opacities, sh_dc, sh_rest, ctx.together, ctx.packed_camera,
                                   *camera_args[7:11], sh_degree, opacity_aware_radius, antialiased)
        else:
            outputs = _scalar_forward(means, quats, scales, opacities, sh_dc, sh_rest, ctx.together, camera_args,
                                      ctx.packed_camera, sh_degree, opacity_aware_radius, antialiased)
        means2d, conics, depths, colors, compensations, radii, tile_min, tile_max, alpha_extent = outputs
        # The SIMD backward reads the forward's colours for the clamp instead of evaluating the SH again.
        ctx.save_for_backward(means, quats, scales, sh_dc, sh_rest, colors if ctx.simd else None)
        ctx.camera_args, ctx.sh_degree, ctx.antialiased = camera_args, sh_degree, antialiased
        ctx.view_like = None if world_to_camera is None else world_to_camera.detach()
        ctx.deferral = deferral
        ctx.mark_non_differentiable(radii, tile_min, tile_max, alpha_extent)
        return means2d, conics, depths, colors, compensations, radii, tile_min, tile_max, alpha_extent

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths, grad_colors, grad_compensations, *_no_grad):
        means, quats, scales, sh_dc, sh_rest, colors = ctx.saved_tensors
        upstream = [torch.zeros_like(like) if g is None else g.contiguous() for g, like in (
            (grad_means2d, means[:, :2]), (grad_conics, means), (grad_depths, means[:, 0]), (grad_colors, means),
            (grad_compensations, means[:, 0]))]
        view_grad = ctx.needs_input_grad[10]
        if ctx.deferral is not None:  # the update finishes these gradients (deferred.py)
            left = ctx.deferral.regularizers
            ctx.deferral.pending = deferred.DeferredBackward(
                means, quats, scales, sh_dc, sh_rest, ctx.camera_args, ctx.packed_camera, ctx.sh_degree,
                ctx.antialiased, colors, upstream, ctx.simd,
                ctx.deferral.activations[1] if left is not None else None, left)
            ctx.deferral = None
            return (None,) * 12
        if ctx.simd:
            grads, per_gaussian_view = simd.project_backward(
                means, quats, scales, sh_dc, sh_rest, ctx.together, ctx.packed_camera, *ctx.camera_args[7:9],
                ctx.sh_degree, ctx.antialiased, colors, upstream, view_grad)
        else:
            grads, per_gaussian_view = _scalar_backward(means, quats, scales, sh_dc, sh_rest, ctx.together,
                                                        ctx.packed_camera, *ctx.camera_args[7:9], ctx.sh_degree,
                                                        ctx.antialiased, upstream, view_grad)
        grad_rest = None if ctx.together else grads[4]
        grad_view = None
        if view_grad:
            summed = per_gaussian_view.sum(dim=0)
            grad_view = torch.zeros(4, 4, dtype=means.dtype, device=means.device)
            grad_view[:3, :3] = summed[:9].reshape(3, 3)
            grad_view[:3, 3] = summed[9:]
            grad_view = grad_view.to(ctx.view_like)
        return (*grads[:4], grad_rest, None, None, None, None, None, grad_view, None)


def gradients_of(pending: deferred.DeferredBackward) -> list[torch.Tensor]:
    """The parameter gradients a deferred backward owes (means, quats, scales, sh_dc, sh_rest), from the kernels its
    forward ran."""
    if pending.simd:
        grads, _ = simd.project_backward(pending.means, pending.quats, pending.scales, pending.sh_dc, pending.sh_rest,
                                         False, pending.camera, pending.width, pending.height, pending.sh_degree,
                                         pending.antialiased, pending.colors, pending.upstream, False)
    else:
        grads, _ = _scalar_backward(pending.means, pending.quats, pending.scales, pending.sh_dc, pending.sh_rest,
                                    False, pending.camera, pending.width, pending.height, pending.sh_degree,
                                    pending.antialiased, pending.upstream, False)
    return grads


def _scalar_forward(means, quats, scales, opacities, sh_dc, sh_rest, together: bool, camera_args: tuple,
                    camera: torch.Tensor, sh_degree: int, opacity_aware_radius: bool,
                    antialiased: bool) -> list[torch.Tensor]:
    """The forward outputs from the Warp kernel (one thread per Gaussian): CUDA, float64, or the CPU's second
    opinion."""
    n, dtype, device = means.shape[0], means.dtype, means.device
    scalar = warp_scalar(dtype)
    empty = functools.partial(torch.empty, dtype=dtype, device=device)
    empty_int = functools.partial(torch.empty, dtype=torch.int32, device=device)
    outputs = [empty(n, 2), empty(n, 3), empty(n), empty(n, 3), empty(n), empty_int(n), empty_int(n, 2),
               empty_int(n, 2), empty(n, 2)]
    means2d, conics, depths, colors, compensations, radii, tile_min, tile_max, alpha_extent = outputs
    forward_kernel, _ = projection_kernels(scalar)
    run_ranges(forward_kernel, n, device, [
        warp_view(camera), *camera_args[7:11], sh_degree, int(opacity_aware_radius), int(antialiased),
        _vector_view(means, 3, scalar), _vector_view(quats, 4, scalar), _vector_view(scales, 3, scalar),
        _scalar_view(opacities), _vector_view(sh_dc, 3, scalar), _vector_view(sh_rest, 3, scalar),
        int(together), _vector_view(means2d, 2, scalar), _vector_view(conics, 3, scalar),
        _scalar_view(depths), _vector_view(colors, 3, scalar), _scalar_view(compensations),
        _scalar_view(radii), _scalar_view(tile_min), _scalar_view(tile_max), _vector_view(alpha_extent, 2, scalar)])
    return outputs


def _scalar_backward(means, quats, scales, sh_dc, sh_rest, together: bool, camera: torch.Tensor, width: int,
                     height: int, sh_degree: int, antialiased: bool, upstream: list[torch.Tensor], view_grad: bool):
    """The Warp backward kernel's gradients: (means, quats, scales, sh_dc, sh_rest) and the per-Gaussian view share
    (None without view_grad), as cpu_simd.project_backward returns them."""
    n, scalar = means.shape[0], warp_scalar(means.dtype)
    grads = [torch.zeros_like(t) for t in (means, quats, scales, sh_dc)]
    grads.append(grads[3] if together else torch.zeros_like(sh_rest))
    _, backward_kernel = projection_kernels(scalar)
    per_gaussian_view = torch.zeros((n if view_grad else 1, 12), dtype=means.dtype, device=means.device)
    run_ranges(backward_kernel, n, means.device, [
        warp_view(camera), width, height, sh_degree, int(antialiased),
        _vector_view(means, 3, scalar), _vector_view(quats, 4, scalar), _vector_view(scales, 3, scalar),
        _vector_view(sh_dc, 3, scalar), _vector_view(sh_rest, 3, scalar), int(together),
        _vector_view(upstream[0], 2, scalar), _vector_view(upstream[1], 3, scalar), _scalar_view(upstream[2]),
        _vector_view(upstream[3], 3, scalar), _scalar_view(upstream[4]),
        _vector_view(grads[0], 3, scalar), _vector_view(grads[1], 4, scalar), _vector_view(grads[2], 3, scalar),
        _vector_view(grads[3], 3, scalar), _vector_view(grads[4], 3, scalar),
        int(view_grad), _scalar_view(per_gaussian_view)])
    return grads, per_gaussian_view if view_grad else None


def _camera_arguments(camera: Camera, near: float, far: float, eps2d: float) -> tuple:
    """(rotation row-major, translation, centre, fx, fy, cx, cy, width, height, tiles_x, tiles_y, near, far, eps2d) as
    Python numbers, read once per camera (Camera.pose_numbers, focal_and_centre: from its host copy where it has one;
    a pose being refined has none: it is read from the device)."""
    return (*camera.pose_numbers, *camera.focal_and_centre, int(camera.width), int(camera.height),
            -(-camera.width // TILE_SIZE), -(-camera.height // TILE_SIZE), float(near), float(far), float(eps2d))


_PACKED_KEPT = 1024  # cameras whose packed numbers are kept on their device (a capture's views, a few sizes each)
_packed: dict[tuple, torch.Tensor] = {}


def packed_camera(camera_args: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The camera's numbers as the kernels read them, in cpu_simd.CAMERA_LAYOUT's order: an array on the device (the
    Warp kernels' arguments then do not change from view to view) in the kernels' dtype (the SIMD kernel's: float32
    on the CPU). On a GPU made once per camera and kept: a copy there at every step would wait for its queue. On
    the CPU made at each render (nothing waits there), for small arrays kept between many renders' buffers raise the
    process's peak memory. While a camera slot serves (camera_slot.py: a step replayed as a CUDA graph), the slot's
    array."""
    slot = camera_slot.serving()
    served = slot.serve(camera_args, dtype, device) if slot is not None else None
    if served is not None:
        return served
    key = (camera_args, dtype, str(device))
    found = _packed.get(key)
    if found is None:
        rotation, translation, center, fx, fy, cx, cy, _w, _h, _tx, _ty, near, far, eps2d = camera_args
        numbers = [*rotation, *translation, *center, fx, fy, cx, cy, near, far, eps2d]
        assert len(numbers) == len(CAMERA_LAYOUT)
        found = torch.tensor(numbers, dtype=dtype).to(device)
        if device.type == "cuda":
            if len(_packed) >= _PACKED_KEPT:
                _packed.pop(next(iter(_packed)))
            _packed[key] = found
    return found


def fill_slot(slot: camera_slot.CameraSlot, camera: Camera) -> None:
    """Put `camera`'s packed numbers in `slot`, for renders with the settings it served (a copy on the device)."""
    if slot.settings is None or camera_slot.serving() is slot:
        raise ValueError("a camera slot is filled after it has served a render (which sets its size and planes), "
                         "outside serving()")
    width, height, _tiles_x, _tiles_y, near, far, eps2d = slot.settings
    if (int(camera.width), int(camera.height)) != (width, height):
        raise ValueError(f"a camera slot for {width}x{height} renders cannot hold a {camera.width}x{camera.height} "
                         f"camera")
    args = _camera_arguments(camera, near, far, eps2d)
    slot.buffer.copy_(packed_camera(args, slot.buffer.dtype, slot.buffer.device))
    slot.filled = True


def project_and_shade(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      sh: torch.Tensor, camera: Camera, sh_degree: int, *, sh_rest: torch.Tensor | None = None,
                      near: float = NEAR_PLANE, far: float = FAR_PLANE, eps2d: float = LOW_PASS,
                      opacity_aware_radius: bool = False, antialiased: bool = False) -> tuple[Projection, torch.Tensor]:
    """project_gaussians + view_dependent_colors of torch_autograd.py in one kernel -> (Projection, colors [N, 3]).

    `sh` holds every SH coefficient [N, K, 3], or, with `sh_rest` [N, K - 1, 3] given, the DC band [N, 1, 3] only.
    Where the camera's `world_to_camera` requires grad, it gets its gradient too (in its own dtype). Within
    deferred.deferring, the parameters' gradients may be left to the optimizer step (deferred.py).
    """
    camera_args = _camera_arguments(camera, near, far, eps2d)
    view = camera.world_to_camera if camera.world_to_camera.requires_grad else None  # pose refinement
    deferral = deferred.current()
    if deferral is not None and (view is not None or not deferral.accepts(means, quats, scales, sh, sh_rest)):
        deferral = None
    if deferral is not None:
        deferral.taken = True
        if kernels_for(means) == "simd":  # the CPU's fused update can take the regularizers too
            deferral.note_activations(scales, opacities)
    means2d, conics, depths, colors, compensations, radii, tile_min, tile_max, alpha_extent = _ProjectFunction.apply(
        means, quats, scales, sh, sh_rest, opacities, camera_args, sh_degree, opacity_aware_radius, antialiased, view,
        deferral)
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, tile_min=tile_min,
                      tile_max=tile_max, alpha_extent=alpha_extent,
                      compensations=compensations if antialiased else None), colors
