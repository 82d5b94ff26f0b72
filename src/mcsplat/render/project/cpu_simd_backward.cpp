{{PRELUDE}}

    const float* colors_ = (const float*)colors.data;  // the forward's: where it is 0 the clamp stops the gradient
    vf g_mean2d[2], g_conic[3], g_depth_row[1], g_color[3], g_compensation_row[1] = {(vf)0.0f};
{{LOAD_G_MEAN2D}}
{{LOAD_G_CONIC}}
{{LOAD_G_COLOR}}
{{LOAD_G_DEPTH_ROW}}

    if (antialiased) {
{{LOAD_G_COMPENSATION_ROW}}
    }
    const vf g_depth = g_depth_row[0], g_compensation = g_compensation_row[0];
    // Lanes that some gradient reaches (the others are culled, or outside every pixel's list): their outputs are 0.
    const vi reached = (g_mean2d[0] != 0.0f) | (g_mean2d[1] != 0.0f) | (g_conic[0] != 0.0f) | (g_conic[1] != 0.0f)
        | (g_conic[2] != 0.0f) | (g_depth != 0.0f) | (g_color[0] != 0.0f) | (g_color[1] != 0.0f)
        | (g_color[2] != 0.0f) | (g_compensation != 0.0f);
    // The gradients' rows: the whole arrays', or (the fused update, optim/fused_projection.py) the chunk's own from
    // row out_first on.
    float* out_means_ = {{OUT_MEANS}};
    float* out_quats_ = {{OUT_QUATS}};
    float* out_scales_ = {{OUT_SCALES}};
    float* out_dc_ = {{OUT_DC}};
    float* out_rest_ = {{OUT_REST}};
    float* out_view_ = (float*)out_view.data;
    const int out_first = {{OUT_FIRST}};
    const int view_width = view_grad ? 12 : 0;
    if (!any_lane(reached)) {
        for (int l = 0; l < count; ++l) {
            const int i = first + l, o = i - out_first;
            for (int k = 0; k < 3; ++k) { out_means_[3 * o + k] = 0.0f; out_scales_[3 * o + k] = 0.0f; }
            for (int k = 0; k < 4; ++k) out_quats_[4 * o + k] = 0.0f;
            for (int k = 0; k < 3; ++k) out_dc_[o * dc_stride + k] = 0.0f;
            for (int k = 0; k < 3 * rest_count; ++k) out_rest_[o * rest_stride + 3 * rest_shift + k] = 0.0f;
            for (int k = 0; k < view_width; ++k) out_view_[12 * i + k] = 0.0f;
        }
        return;
    }
{{GEOMETRY}}

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
    const float c2_0 = {{SH_C2_0}}f, c2_1 = {{SH_C2_1}}f, c2_2 = {{SH_C2_2}}f, c2_3 = {{SH_C2_3}}f, c2_4 = {{SH_C2_4}}f;
    const float c3_0 = {{SH_C3_0}}f, c3_1 = {{SH_C3_1}}f, c3_2 = {{SH_C3_2}}f, c3_3 = {{SH_C3_3}}f, c3_4 = {{SH_C3_4}}f, c3_5 = {{SH_C3_5}}f;
    const float c3_6 = {{SH_C3_6}}f;
    const vf zero = 0.0f;
    const vf d_x[16] = {zero, zero, zero, (vf)(-{{SH_C1}}f), c2_0 * dy, zero, -2.0f * c2_2 * dx, c2_3 * dz,
        2.0f * c2_4 * dx,
        c3_0 * 6.0f * dx * dy, c3_1 * dy * dz, -c3_2 * 2.0f * dx * dy, -c3_3 * 6.0f * dx * dz,
        c3_4 * (4.0f * zz - 3.0f * xx - yy), c3_5 * 2.0f * dx * dz, c3_6 * 3.0f * (xx - yy)};
    const vf d_y[16] = {zero, (vf)(-{{SH_C1}}f), zero, zero, c2_0 * dx, c2_1 * dz, -2.0f * c2_2 * dy, zero,
        -2.0f * c2_4 * dy, c3_0 * 3.0f * (xx - yy), c3_1 * dx * dz, c3_2 * (4.0f * zz - xx - 3.0f * yy),
        -c3_3 * 6.0f * dy * dz, -c3_4 * 2.0f * dx * dy, -c3_5 * 2.0f * dy * dz, -c3_6 * 6.0f * dx * dy};
    const vf d_z[16] = {zero, zero, (vf){{SH_C1}}f, zero, zero, c2_1 * dy, 4.0f * c2_2 * dz, c2_3 * dx, zero,
        zero, c3_1 * dx * dy, c3_2 * 8.0f * dy * dz, c3_3 * (6.0f * zz - 3.0f * xx - 3.0f * yy),
        c3_4 * 8.0f * dx * dz, c3_5 * (xx - yy), zero};
    vf g_d[3] = {zero, zero, zero};
    for (int l = 0; l < count; ++l) {
        const int i = first + l;
        float* dc_out = out_dc_ + (i - out_first) * dc_stride;
        float* rest_out = out_rest_ + (i - out_first) * rest_stride + 3 * rest_shift;
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
{{STORE_OUT_MEANS}}
{{STORE_OUT_SCALES}}
{{STORE_OUT_QUATS}}

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
