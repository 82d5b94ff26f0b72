"""SIMD projection and SH colour for the CPU: 16 Gaussians in 16 vector lanes, forward and hand-written backward.

The same maths, conventions and outputs as the Warp kernels of render/project_kernel.py (which stay the CUDA path,
the float64 path and the tests' second opinion), written as C++ snippets (`wp.func_native`) over clang vector types
because Warp's kernel language runs one Gaussian per thread and does not vectorise on the CPU. One kernel thread
takes a chunk of 16 consecutive Gaussians: the geometry (camera space, the Jacobian, the 3D and 2D covariances, the
conic, the screen extent, and their chain rule backwards) runs on all 16 at once; the SH colour, whose coefficients
lie in each Gaussian's own row, runs lane by lane over the basis values the vectors computed. The last chunk repeats
its last Gaussian in the spare lanes and stores only its own.

The backward writes every entry of its outputs (zeros for a Gaussian no gradient reaches and for SH bands above the
active degree), so its buffers need no zero-fill first, and it reads the forward's colours for the clamp at 0 instead
of evaluating the SH again: the gradient passes where a colour is above 0 (the Warp kernel also passes it where the
colour before the clamp is exactly 0: the one place the two can differ). Float32 only: project_kernel.py chooses
these kernels for float32 tensors on the CPU. Each thread writes only its own Gaussians, so the result does not
depend on timing.

Camera numbers come packed in one float32 array (see CAMERA_LAYOUT); the logarithm is a polynomial (a libm call
would stop the lanes from vectorising), relative error about 1e-7, used only for the screen extent, which has margins.
"""

from __future__ import annotations

import warp as wp

from ...compute.cpu_target import kernel_flags
from ...compute.simd_lanes import LANES, VECTOR_TYPES, lanes_in, lanes_out
from ...geometry.sh import SH_C0, SH_C1, SH_C2, SH_C3
from ..constants import TILE_SIZE

# Order of the packed camera numbers: world-to-camera rotation (row-major), translation, camera centre, intrinsics,
# near and far planes, the low-pass filter.
CAMERA_LAYOUT = ("r00", "r01", "r02", "r10", "r11", "r12", "r20", "r21", "r22", "t0", "t1", "t2",
                 "centre_x", "centre_y", "centre_z", "fx", "fy", "cx", "cy", "near", "far", "eps2d")


_PRELUDE = f"""
{VECTOR_TYPES}
    auto select = [](vi mask, vf a, vf b) -> vf {{ return (vf)(((vi)a & mask) | ((vi)b & ~mask)); }};
    auto vmin = [](vf a, vf b) -> vf {{ return __builtin_elementwise_min(a, b); }};
    auto vmax = [](vf a, vf b) -> vf {{ return __builtin_elementwise_max(a, b); }};
    auto vsqrt = [](vf x) -> vf {{ return __builtin_elementwise_sqrt(x); }};
    auto any_lane = [](vi mask) -> bool {{ return __builtin_reduce_or(mask) != 0; }};
    // Natural log of positive normal numbers (Cephes' logf: mantissa in [sqrt(1/2), sqrt(2)), a degree-9 polynomial).
    auto vlog = [=](vf x) -> vf {{
        vi bits = (vi)x;
        vi e = ((bits >> 23) & 0xff) - 126;
        vf m = (vf)((bits & 0x807fffff) | 0x3f000000);  // in [0.5, 1)
        vi small = m < 0.707106781186547524f;
        e += small;  // small is -1 where true
        m = select(small, m + m, m) - 1.0f;
        vf z = m * m;
        vf y = 7.0376836292e-2f;
        y = y * m - 1.1514610310e-1f;
        y = y * m + 1.1676998740e-1f;
        y = y * m - 1.2420140846e-1f;
        y = y * m + 1.4249322787e-1f;
        y = y * m - 1.6668057665e-1f;
        y = y * m + 2.0000714765e-1f;
        y = y * m - 2.4999993993e-1f;
        y = y * m + 3.3333331174e-1f;
        y = y * m * z;
        vf fe = __builtin_convertvector(e, vf);
        y += -2.12194440e-4f * fe;
        y += -0.5f * z;
        return m + y + 0.693359375f * fe;
    }};

    const int first = {LANES} * chunk;
    const int count = n - first < {LANES} ? n - first : {LANES};
    if (count <= 0) return;
    const float* cam = (const float*)camera.data;
    const float W[3][3] = {{{{cam[0], cam[1], cam[2]}}, {{cam[3], cam[4], cam[5]}}, {{cam[6], cam[7], cam[8]}}}};
    const float t[3] = {{cam[9], cam[10], cam[11]}};
    const float centre[3] = {{cam[12], cam[13], cam[14]}};
    const float fx = cam[15], fy = cam[16], cx = cam[17], cy = cam[18];
    const float near_plane = cam[19], far_plane = cam[20], eps2d = cam[21];
    // Bounds of x/z and y/z for the Jacobian: the field of view widened by 30% on each side (3DGS, gsplat).
    const float tan_fovx = 0.5f * (float)width / fx, tan_fovy = 0.5f * (float)height / fy;
    const float lim_x_neg = cx / fx + 0.3f * tan_fovx, lim_x_pos = ((float)width - cx) / fx + 0.3f * tan_fovx;
    const float lim_y_neg = cy / fy + 0.3f * tan_fovy, lim_y_pos = ((float)height - cy) / fy + 0.3f * tan_fovy;
    const int basis_count = (sh_degree + 1) * (sh_degree + 1);

    // The chunk's Gaussians in lanes (spare lanes repeat the last one).
    const float* means_ = (const float*)means.data;
    const float* quats_ = (const float*)quats.data;
    const float* scales_ = (const float*)scales.data;
    vf mean[3], q_raw[4], s[3];
""" + lanes_in("mean", "means_", 3) + lanes_in("s", "scales_", 3) + lanes_in("q_raw", "quats_", 4)

# Camera space, the Jacobian (its view direction clamped), the rotation of the normalised quaternion, and the 2D
# covariance J W R S S^T R^T W^T J^T with the low-pass on its diagonal: what forward and backward both need.
_GEOMETRY = """
    vf p[3];
    for (int r = 0; r < 3; ++r) p[r] = W[r][0] * mean[0] + W[r][1] * mean[1] + W[r][2] * mean[2] + t[r];
    const vi in_range = (p[2] > near_plane) & (p[2] < far_plane);
    // Culled Gaussians still flow through the maths: a safe depth keeps their (unused) gradients finite.
    const vf z_safe = select(in_range, p[2], (vf)1.0f);
    const vf u = p[0] / z_safe, v = p[1] / z_safe;
    const vf u_clamped = vmin(vmax(u, (vf)(-lim_x_neg)), (vf)lim_x_pos);
    const vf v_clamped = vmin(vmax(v, (vf)(-lim_y_neg)), (vf)lim_y_pos);
    const vf tx = z_safe * u_clamped, ty = z_safe * v_clamped;
    const vf z2 = z_safe * z_safe;
    const vf j00 = fx / z_safe, j11 = fy / z_safe, j02 = -fx * tx / z2, j12 = -fy * ty / z2;

    const vf q_length = vsqrt(q_raw[0] * q_raw[0] + q_raw[1] * q_raw[1] + q_raw[2] * q_raw[2] + q_raw[3] * q_raw[3]);
    const vf q_norm = vmax(q_length, (vf)1e-12f);
    const vf qw = q_raw[0] / q_norm, qx = q_raw[1] / q_norm, qy = q_raw[2] / q_norm, qz = q_raw[3] / q_norm;
    const vf R[3][3] = {
        {1.0f - 2.0f * (qy * qy + qz * qz), 2.0f * (qx * qy - qw * qz), 2.0f * (qx * qz + qw * qy)},
        {2.0f * (qx * qy + qw * qz), 1.0f - 2.0f * (qx * qx + qz * qz), 2.0f * (qy * qz - qw * qx)},
        {2.0f * (qx * qz - qw * qy), 2.0f * (qy * qz + qw * qx), 1.0f - 2.0f * (qx * qx + qy * qy)}};
    vf M[3][3], sigma[3][3], w_sigma[3][3], V[3][3];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) M[r][c] = R[r][c] * s[c];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) sigma[r][c] = M[r][0] * M[c][0] + M[r][1] * M[c][1] + M[r][2] * M[c][2];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            w_sigma[r][c] = W[r][0] * sigma[0][c] + W[r][1] * sigma[1][c] + W[r][2] * sigma[2][c];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            V[r][c] = w_sigma[r][0] * W[c][0] + w_sigma[r][1] * W[c][1] + w_sigma[r][2] * W[c][2];
    vf JV[2][3];  // J V, J = [[j00, 0, j02], [0, j11, j12]]
    for (int c = 0; c < 3; ++c) {
        JV[0][c] = j00 * V[0][c] + j02 * V[2][c];
        JV[1][c] = j11 * V[1][c] + j12 * V[2][c];
    }
    const vf cov00 = JV[0][0] * j00 + JV[0][2] * j02;
    const vf cov01 = JV[0][1] * j11 + JV[0][2] * j12;
    const vf cov11 = JV[1][1] * j11 + JV[1][2] * j12;
    const vf a = cov00 + eps2d, b = cov01, c = cov11 + eps2d;
    const vf det = a * c - b * b;
    const vi valid_conic = in_range & (det > 0.0f);
    const vf det_safe = select(valid_conic, det, (vf)1.0f);

    // The SH basis along the unit camera-to-Gaussian direction (3DGS's order and signs), basis[0] the constant.
    const vf offset_dir[3] = {mean[0] - centre[0], mean[1] - centre[1], mean[2] - centre[2]};
    const vf dir_length = vsqrt(offset_dir[0] * offset_dir[0] + offset_dir[1] * offset_dir[1]
                                + offset_dir[2] * offset_dir[2]);
    const vi has_length = dir_length > 0.0f;
    const vf dx = select(has_length, offset_dir[0] / dir_length, (vf)0.0f);
    const vf dy = select(has_length, offset_dir[1] / dir_length, (vf)0.0f);
    const vf dz = select(has_length, offset_dir[2] / dir_length, (vf)0.0f);
    const vf xx = dx * dx, yy = dy * dy, zz = dz * dz;
    vf basis[16];
    basis[0] = SH_C0_;
    basis[1] = -SH_C1_ * dy; basis[2] = SH_C1_ * dz; basis[3] = -SH_C1_ * dx;
    basis[4] = SH_C2_0_ * dx * dy; basis[5] = SH_C2_1_ * dy * dz; basis[6] = SH_C2_2_ * (2.0f * zz - xx - yy);
    basis[7] = SH_C2_3_ * dx * dz; basis[8] = SH_C2_4_ * (xx - yy);
    basis[9] = SH_C3_0_ * dy * (3.0f * xx - yy); basis[10] = SH_C3_1_ * dx * dy * dz;
    basis[11] = SH_C3_2_ * dy * (4.0f * zz - xx - yy); basis[12] = SH_C3_3_ * dz * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    basis[13] = SH_C3_4_ * dx * (4.0f * zz - xx - yy); basis[14] = SH_C3_5_ * dz * (xx - yy);
    basis[15] = SH_C3_6_ * dx * (xx - 3.0f * yy);
    const float* rest_ = (const float*)sh_rest.data;
"""

_FORWARD_BODY = (_PRELUDE + _GEOMETRY + """
    // The colour, + 0.5 and clamped at 0, lane by lane (each Gaussian's coefficients are one row).
    const float* dc_ = (const float*)sh_dc.data;
    float* colors_ = (float*)out_colors.data;
    for (int l = 0; l < count; ++l) {
        const float* dc_row = dc_ + (first + l) * dc_stride;
        const float* rest_row = rest_ + (first + l) * rest_stride + 3 * rest_shift;
        float sum[3] = {basis[0][l] * dc_row[0], basis[0][l] * dc_row[1], basis[0][l] * dc_row[2]};
        for (int k = 1; k < basis_count; ++k) {
            const float weight = basis[k][l];
            for (int ch = 0; ch < 3; ++ch) sum[ch] += weight * rest_row[3 * (k - 1) + ch];
        }
        for (int ch = 0; ch < 3; ++ch) colors_[3 * (first + l) + ch] = sum[ch] + 0.5f > 0.0f ? sum[ch] + 0.5f : 0.0f;
    }
    const float* opacities_ = (const float*)opacities.data;
    vf opacity_row[1];
""" + lanes_in("opacity_row", "opacities_", 1) + f"""
    const vf opacity = opacity_row[0];
    const vf conic[3] = {{c / det_safe, -b / det_safe, a / det_safe}};
    // Mip-Splatting's 2D filter: the opacity shrinks by the ratio of the areas before and after the low-pass.
    const vf compensation = antialiased ? vsqrt(vmax((cov00 * cov11 - b * b) / det_safe, (vf)0.0f)) : (vf)1.0f;
    const vf mean2d[2] = {{fx * p[0] / z_safe + cx, fy * p[1] / z_safe + cy}};

    // Screen extent (no gradient): radius from the largest eigenvalue, the tiles it touches, the alpha box.
    const vf mid = 0.5f * (a + c);
    const vf lambda_max = mid + vsqrt(vmax(0.25f * (a - c) * (a - c) + b * b, (vf)0.1f));
    vf extent = 3.0f;
    vi valid = valid_conic;
    if (opacity_aware_radius) {{
        // Beyond sqrt(2 ln(255 o)) sigma the alpha falls under 1/255 and the pixel is skipped anyway.
        extent = vmin(vsqrt(vmax(2.0f * vlog(vmax(255.0f * opacity, (vf)1.0f)), (vf)0.0f)), (vf)3.0f);
        valid &= 255.0f * opacity > 1.0f;
    }}
    const vf radius = __builtin_elementwise_ceil(extent * vsqrt(vmax(lambda_max, (vf)0.0f)));
    const float tile = {TILE_SIZE}.0f;
    auto tile_of = [&](vf x, int limit, float shift) -> vf {{
        return vmin(vmax(__builtin_elementwise_floor(x / tile) + shift, (vf)0.0f), (vf)(float)limit);
    }};
    const vf lo_x = tile_of(mean2d[0] - radius, tiles_x, 0.0f), hi_x = tile_of(mean2d[0] + radius, tiles_x, 1.0f);
    const vf lo_y = tile_of(mean2d[1] - radius, tiles_y, 0.0f), hi_y = tile_of(mean2d[1] + radius, tiles_y, 1.0f);
    // Finite: |x| <= FLT_MAX (false for inf and NaN).
    const vi finite = ((vf)((vi)mean2d[0] & 0x7fffffff) <= 3.40282347e38f)
        & ((vf)((vi)mean2d[1] & 0x7fffffff) <= 3.40282347e38f);
    valid &= (radius > 0.0f) & (hi_x > lo_x) & (hi_y > lo_y) & finite;
    // Half-widths of the box outside which o exp(-d^T Q d / 2) < 1/255 (see project._alpha_extent).
    const vf k_box = vmax(2.0f * vlog(vmax(255.0f * opacity, (vf)1e-30f)), (vf)0.0f);
    const vi has_box = k_box > 0.0f;
    const vf box_x = select(has_box, vsqrt(k_box * vmax(a, (vf)0.0f)) * 1.001f + 0.01f, (vf)0.0f);
    const vf box_y = select(has_box, vsqrt(k_box * vmax(c, (vf)0.0f)) * 1.001f + 0.01f, (vf)0.0f);

    float* means2d_ = (float*)out_means2d.data;
    float* conics_ = (float*)out_conics.data;
    float* depths_ = (float*)out_depths.data;
    float* compensations_ = (float*)out_compensations.data;
    int* radii_ = (int*)out_radii.data;
    int* tile_min_ = (int*)out_tile_min.data;
    int* tile_max_ = (int*)out_tile_max.data;
    float* alpha_extent_ = (float*)out_alpha_extent.data;
    const vi kept_radius = valid & __builtin_convertvector(radius, vi);
    const vi kept_lo_x = valid & __builtin_convertvector(lo_x, vi);
    const vi kept_lo_y = valid & __builtin_convertvector(lo_y, vi);
    const vi kept_hi_x = valid & __builtin_convertvector(hi_x, vi);
    const vi kept_hi_y = valid & __builtin_convertvector(hi_y, vi);
""" + lanes_out(["mean2d[0]", "mean2d[1]"], "means2d_") + lanes_out(["conic[0]", "conic[1]", "conic[2]"], "conics_")
    + lanes_out(["p[2]"], "depths_") + lanes_out(["compensation"], "compensations_")
    + lanes_out(["kept_radius"], "radii_", "i") + lanes_out(["kept_lo_x", "kept_lo_y"], "tile_min_", "i")
    + lanes_out(["kept_hi_x", "kept_hi_y"], "tile_max_", "i") + lanes_out(["box_x", "box_y"], "alpha_extent_"))

_BACKWARD_BODY = (_PRELUDE + """
    const float* g_means2d_ = (const float*)grad_means2d.data;
    const float* g_conics_ = (const float*)grad_conics.data;
    const float* g_depths_ = (const float*)grad_depths.data;
    const float* g_colors_ = (const float*)grad_colors.data;
    const float* colors_ = (const float*)colors.data;  // the forward's: where it is 0 the clamp stops the gradient
    const float* g_compensations_ = (const float*)grad_compensations.data;
    vf g_mean2d[2], g_conic[3], g_depth_row[1], g_color[3], g_compensation_row[1] = {(vf)0.0f};
""" + lanes_in("g_mean2d", "g_means2d_", 2) + lanes_in("g_conic", "g_conics_", 3)
    + lanes_in("g_color", "g_colors_", 3) + lanes_in("g_depth_row", "g_depths_", 1) + """
    if (antialiased) {""" + lanes_in("g_compensation_row", "g_compensations_", 1) + """
    }
    const vf g_depth = g_depth_row[0], g_compensation = g_compensation_row[0];
    // Lanes that some gradient reaches (the others are culled, or outside every pixel's list): their outputs are 0.
    const vi reached = (g_mean2d[0] != 0.0f) | (g_mean2d[1] != 0.0f) | (g_conic[0] != 0.0f) | (g_conic[1] != 0.0f)
        | (g_conic[2] != 0.0f) | (g_depth != 0.0f) | (g_color[0] != 0.0f) | (g_color[1] != 0.0f)
        | (g_color[2] != 0.0f) | (g_compensation != 0.0f);
    float* out_means_ = (float*)out_means.data;
    float* out_quats_ = (float*)out_quats.data;
    float* out_scales_ = (float*)out_scales.data;
    float* out_dc_ = (float*)out_dc.data;
    float* out_rest_ = (float*)out_rest.data;
    float* out_view_ = (float*)out_view.data;
    const int view_width = view_grad ? 12 : 0;
    if (!any_lane(reached)) {
        for (int l = 0; l < count; ++l) {
            const int i = first + l;
            for (int k = 0; k < 3; ++k) { out_means_[3 * i + k] = 0.0f; out_scales_[3 * i + k] = 0.0f; }
            for (int k = 0; k < 4; ++k) out_quats_[4 * i + k] = 0.0f;
            for (int k = 0; k < 3; ++k) out_dc_[i * dc_stride + k] = 0.0f;
            for (int k = 0; k < 3 * rest_count; ++k) out_rest_[i * rest_stride + 3 * rest_shift + k] = 0.0f;
            for (int k = 0; k < view_width; ++k) out_view_[12 * i + k] = 0.0f;
        }
        return;
    }
""" + _GEOMETRY + """
    // ---- conic = (c, -b, a) / det
    const vf g_det = -(g_conic[0] * c - g_conic[1] * b + g_conic[2] * a) / (det_safe * det_safe);
    vf g_a = g_conic[2] / det_safe, g_b = -g_conic[1] / det_safe, g_c = g_conic[0] / det_safe;
    g_a = select(valid_conic, g_a + g_det * c, g_a);
    g_b = select(valid_conic, g_b - 2.0f * g_det * b, g_b);
    g_c = select(valid_conic, g_c + g_det * a, g_c);
    if (antialiased) {
        // ---- compensation = sqrt(ratio), ratio = det((a, b; b, c) - eps2d I) / det
        const vf ratio = ((a - eps2d) * (c - eps2d) - b * b) / det_safe;
        const vi takes = valid_conic & (g_compensation != 0.0f) & (ratio > 0.0f);
        const vf g_ratio = g_compensation / (2.0f * vsqrt(select(takes, ratio, (vf)1.0f)));
        g_a = select(takes, g_a + g_ratio * ((c - eps2d) - ratio * c) / det_safe, g_a);
        g_b = select(takes, g_b - g_ratio * 2.0f * b * (1.0f - ratio) / det_safe, g_b);
        g_c = select(takes, g_c + g_ratio * ((a - eps2d) - ratio * a) / det_safe, g_c);
    }
    // ---- cov2d = J V J^T (the forward reads cov2d[0, 1] only: G = [[g_a, g_b], [0, g_c]])
    // dJ = (G + G^T) J V, of which the four entries J depends on.
    const vf g_j00 = 2.0f * g_a * JV[0][0] + g_b * JV[1][0];
    const vf g_j02 = 2.0f * g_a * JV[0][2] + g_b * JV[1][2];
    const vf g_j11 = g_b * JV[0][1] + 2.0f * g_c * JV[1][1];
    const vf g_j12 = g_b * JV[0][2] + 2.0f * g_c * JV[1][2];
    // dV = J^T G J, kept symmetrised (dV + dV^T): only that reaches Sigma and W.
    const vf GJ[2][3] = {{g_a * j00, g_b * j11, g_a * j02 + g_b * j12}, {(vf)0.0f, g_c * j11, g_c * j12}};
    const vf J[2][3] = {{j00, (vf)0.0f, j02}, {(vf)0.0f, j11, j12}};
    vf g_v[3][3], g_v_sym[3][3];
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col) g_v[r][col] = J[0][r] * GJ[0][col] + J[1][r] * GJ[1][col];
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col) g_v_sym[r][col] = g_v[r][col] + g_v[col][r];
    // ---- V = W Sigma W^T, Sigma = M M^T, M = R(q) diag(s)
    vf tmp[3][3], g_sigma_sym[3][3], g_m[3][3];
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col)
            tmp[r][col] = g_v_sym[r][0] * W[0][col] + g_v_sym[r][1] * W[1][col] + g_v_sym[r][2] * W[2][col];
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col)
            g_sigma_sym[r][col] = W[0][r] * tmp[0][col] + W[1][r] * tmp[1][col] + W[2][r] * tmp[2][col];
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col)
            g_m[r][col] = g_sigma_sym[r][0] * M[0][col] + g_sigma_sym[r][1] * M[1][col]
                + g_sigma_sym[r][2] * M[2][col];
    vf g_rot[3][3], g_scale[3] = {(vf)0.0f, (vf)0.0f, (vf)0.0f};
    for (int r = 0; r < 3; ++r)
        for (int col = 0; col < 3; ++col) {
            g_rot[r][col] = g_m[r][col] * s[col];
            g_scale[col] += g_m[r][col] * R[r][col];
        }
    vf g_q[4] = {
        2.0f * (-qz * g_rot[0][1] + qy * g_rot[0][2] + qz * g_rot[1][0] - qx * g_rot[1][2] - qy * g_rot[2][0]
                + qx * g_rot[2][1]),
        2.0f * (qy * g_rot[0][1] + qz * g_rot[0][2] + qy * g_rot[1][0] - 2.0f * qx * g_rot[1][1] - qw * g_rot[1][2]
                + qz * g_rot[2][0] + qw * g_rot[2][1] - 2.0f * qx * g_rot[2][2]),
        2.0f * (-2.0f * qy * g_rot[0][0] + qx * g_rot[0][1] + qw * g_rot[0][2] + qx * g_rot[1][0]
                + qz * g_rot[1][2] - qw * g_rot[2][0] + qz * g_rot[2][1] - 2.0f * qy * g_rot[2][2]),
        2.0f * (-2.0f * qz * g_rot[0][0] - qw * g_rot[0][1] + qx * g_rot[0][2] + qw * g_rot[1][0]
                - 2.0f * qz * g_rot[1][1] + qy * g_rot[1][2] + qx * g_rot[2][0] + qy * g_rot[2][1])};
    // Through the normalisation (under the 1e-12 clamp the norm is a constant).
    const vf q_dot = qw * g_q[0] + qx * g_q[1] + qy * g_q[2] + qz * g_q[3];
    const vi normalised = q_length >= 1e-12f;
    const vf q_unit[4] = {qw, qx, qy, qz};
    for (int k = 0; k < 4; ++k) g_q[k] = select(normalised, g_q[k] - q_unit[k] * q_dot, g_q[k]) / q_norm;

    // ---- the Jacobian's dependence on the camera-space position
    vf g_z_safe = (-fx * g_j00 - fy * g_j11) / z2 + 2.0f * (fx * tx * g_j02 + fy * ty * g_j12) / (z2 * z_safe);
    const vf g_tx = -fx * g_j02 / z2, g_ty = -fy * g_j12 / z2;
    const vi u_inside = (u >= -lim_x_neg) & (u <= lim_x_pos);
    const vi v_inside = (v >= -lim_y_neg) & (v <= lim_y_pos);
    vf g_p[3];
    g_p[0] = select(u_inside, g_tx, (vf)0.0f);
    g_p[1] = select(v_inside, g_ty, (vf)0.0f);
    g_z_safe += select(u_inside, (vf)0.0f, g_tx * u_clamped) + select(v_inside, (vf)0.0f, g_ty * v_clamped);
    // ---- means2d = (fx x / z + cx, fy y / z + cy), depth = z
    g_p[0] += g_mean2d[0] * fx / z_safe;
    g_p[1] += g_mean2d[1] * fy / z_safe;
    g_z_safe -= (g_mean2d[0] * fx * p[0] + g_mean2d[1] * fy * p[1]) / z2;
    g_p[2] = g_depth + select(in_range, g_z_safe, (vf)0.0f);
    vf g_mean[3];
    for (int k = 0; k < 3; ++k) g_mean[k] = W[0][k] * g_p[0] + W[1][k] * g_p[1] + W[2][k] * g_p[2];

    // ---- colour = max(SH(d) + 0.5, 0): the basis's derivatives along d, then lane by lane the coefficients' rows.
    vf d_basis[3][16];
    const float c2_0 = SH_C2_0_, c2_1 = SH_C2_1_, c2_2 = SH_C2_2_, c2_3 = SH_C2_3_, c2_4 = SH_C2_4_;
    const float c3_0 = SH_C3_0_, c3_1 = SH_C3_1_, c3_2 = SH_C3_2_, c3_3 = SH_C3_3_, c3_4 = SH_C3_4_, c3_5 = SH_C3_5_;
    const float c3_6 = SH_C3_6_;
    const vf zero = 0.0f;
    const vf d_x[16] = {zero, zero, zero, (vf)(-SH_C1_), c2_0 * dy, zero, -2.0f * c2_2 * dx, c2_3 * dz,
        2.0f * c2_4 * dx,
        c3_0 * 6.0f * dx * dy, c3_1 * dy * dz, -c3_2 * 2.0f * dx * dy, -c3_3 * 6.0f * dx * dz,
        c3_4 * (4.0f * zz - 3.0f * xx - yy), c3_5 * 2.0f * dx * dz, c3_6 * 3.0f * (xx - yy)};
    const vf d_y[16] = {zero, (vf)(-SH_C1_), zero, zero, c2_0 * dx, c2_1 * dz, -2.0f * c2_2 * dy, zero,
        -2.0f * c2_4 * dy, c3_0 * 3.0f * (xx - yy), c3_1 * dx * dz, c3_2 * (4.0f * zz - xx - 3.0f * yy),
        -c3_3 * 6.0f * dy * dz, -c3_4 * 2.0f * dx * dy, -c3_5 * 2.0f * dy * dz, -c3_6 * 6.0f * dx * dy};
    const vf d_z[16] = {zero, zero, (vf)SH_C1_, zero, zero, c2_1 * dy, 4.0f * c2_2 * dz, c2_3 * dx, zero,
        zero, c3_1 * dx * dy, c3_2 * 8.0f * dy * dz, c3_3 * (6.0f * zz - 3.0f * xx - 3.0f * yy),
        c3_4 * 8.0f * dx * dz, c3_5 * (xx - yy), zero};
    vf g_d[3] = {zero, zero, zero};
    for (int l = 0; l < count; ++l) {
        const int i = first + l;
        float* dc_out = out_dc_ + i * dc_stride;
        float* rest_out = out_rest_ + i * rest_stride + 3 * rest_shift;
        if (!reached[l]) {
            for (int k = 0; k < 3; ++k) dc_out[k] = 0.0f;
            for (int k = 0; k < 3 * rest_count; ++k) rest_out[k] = 0.0f;
            continue;
        }
        const float* rest_row = rest_ + i * rest_stride + 3 * rest_shift;
        float g[3];
        for (int ch = 0; ch < 3; ++ch) g[ch] = colors_[3 * i + ch] > 0.0f ? g_color[ch][l] : 0.0f;
        for (int ch = 0; ch < 3; ++ch) dc_out[ch] = basis[0][l] * g[ch];
        float sum_x = 0.0f, sum_y = 0.0f, sum_z = 0.0f;
        for (int k = 1; k < basis_count; ++k) {
            const float* coefficient = rest_row + 3 * (k - 1);
            const float along = g[0] * coefficient[0] + g[1] * coefficient[1] + g[2] * coefficient[2];
            for (int ch = 0; ch < 3; ++ch) rest_out[3 * (k - 1) + ch] = basis[k][l] * g[ch];
            sum_x += along * d_x[k][l]; sum_y += along * d_y[k][l]; sum_z += along * d_z[k][l];
        }
        for (int k = 3 * (basis_count - 1); k < 3 * rest_count; ++k) rest_out[k] = 0.0f;
        g_d[0][l] = sum_x; g_d[1][l] = sum_y; g_d[2][l] = sum_z;
    }
    // d = offset / |offset|: the gradient of the offset (mean - camera centre) is (g_d - d (d . g_d)) / |offset|.
    const vf d_dot = dx * g_d[0] + dy * g_d[1] + dz * g_d[2];
    const vf d_unit[3] = {dx, dy, dz};
    vf g_offset[3];
    for (int k = 0; k < 3; ++k)
        g_offset[k] = select(has_length, (g_d[k] - d_unit[k] * d_dot) / dir_length, (vf)0.0f);

    vf kept_mean[3], kept_scale[3], kept_q[4];
    for (int k = 0; k < 3; ++k) {
        kept_mean[k] = select(reached, g_mean[k] + g_offset[k], (vf)0.0f);
        kept_scale[k] = select(reached, g_scale[k], (vf)0.0f);
    }
    for (int k = 0; k < 4; ++k) kept_q[k] = select(reached, g_q[k], (vf)0.0f);
""" + lanes_out(["kept_mean[0]", "kept_mean[1]", "kept_mean[2]"], "out_means_")
    + lanes_out(["kept_scale[0]", "kept_scale[1]", "kept_scale[2]"], "out_scales_")
    + lanes_out(["kept_q[0]", "kept_q[1]", "kept_q[2]", "kept_q[3]"], "out_quats_") + """
    if (view_grad) {
        // p = W mean + t; V = W Sigma W^T; camera centre = -W^T t (the colour's view direction):
        // dW = g_p mean^T + (dV + dV^T) W Sigma + t g_offset^T, dt = g_p + W g_offset.
        vf g_w[3][3], g_t[3];
        for (int r = 0; r < 3; ++r) {
            for (int col = 0; col < 3; ++col)
                g_w[r][col] = g_p[r] * mean[col] + g_v_sym[r][0] * w_sigma[0][col] + g_v_sym[r][1] * w_sigma[1][col]
                    + g_v_sym[r][2] * w_sigma[2][col] + t[r] * g_offset[col];
            g_t[r] = g_p[r] + W[r][0] * g_offset[0] + W[r][1] * g_offset[1] + W[r][2] * g_offset[2];
        }
        for (int l = 0; l < count; ++l) {
            float* row = out_view_ + 12 * (first + l);
            const bool on = reached[l] != 0;
            for (int r = 0; r < 3; ++r) {
                for (int col = 0; col < 3; ++col) row[3 * r + col] = on ? g_w[r][col][l] : 0.0f;
                row[9 + r] = on ? g_t[r][l] : 0.0f;
            }
        }
    }
""")


def _with_constants(body: str) -> str:
    """The SH constants as float literals (the snippets name them SH_C1_, SH_C2_0_, ...)."""
    names = {"SH_C0_": SH_C0, "SH_C1_": SH_C1}
    names.update({f"SH_C2_{k}_": value for k, value in enumerate(SH_C2)})
    names.update({f"SH_C3_{k}_": value for k, value in enumerate(SH_C3)})
    for name, value in names.items():
        body = body.replace(name, f"{float(value)!r}f")
    return body


# Same options as the compositing kernels (render/cpu/composite.py): 512-bit vectors where the CPU has them, fused
# multiply-add.
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512 -ffp-contract=fast")})

_int_array = wp.array(dtype=wp.int32)
_float_array = wp.array(dtype=wp.float32)


@wp.func_native(_with_constants(_FORWARD_BODY))
def _project_chunk(chunk: int, n: int, camera: _float_array, width: int, height: int, tiles_x: int, tiles_y: int,
                   sh_degree: int, opacity_aware_radius: int, antialiased: int,
                   means: _float_array, quats: _float_array, scales: _float_array, opacities: _float_array,
                   sh_dc: _float_array, sh_rest: _float_array, dc_stride: int, rest_stride: int, rest_shift: int,
                   out_means2d: _float_array, out_conics: _float_array, out_depths: _float_array,
                   out_colors: _float_array, out_compensations: _float_array, out_radii: _int_array,
                   out_tile_min: _int_array, out_tile_max: _int_array, out_alpha_extent: _float_array): ...


@wp.func_native(_with_constants(_BACKWARD_BODY))
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
