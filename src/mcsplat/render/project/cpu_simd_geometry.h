
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
    basis[0] = {{SH_C0}}f;
    basis[1] = -{{SH_C1}}f * dy; basis[2] = {{SH_C1}}f * dz; basis[3] = -{{SH_C1}}f * dx;
    basis[4] = {{SH_C2_0}}f * dx * dy; basis[5] = {{SH_C2_1}}f * dy * dz; basis[6] = {{SH_C2_2}}f * (2.0f * zz - xx - yy);
    basis[7] = {{SH_C2_3}}f * dx * dz; basis[8] = {{SH_C2_4}}f * (xx - yy);
    basis[9] = {{SH_C3_0}}f * dy * (3.0f * xx - yy); basis[10] = {{SH_C3_1}}f * dx * dy * dz;
    basis[11] = {{SH_C3_2}}f * dy * (4.0f * zz - xx - yy); basis[12] = {{SH_C3_3}}f * dz * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    basis[13] = {{SH_C3_4}}f * dx * (4.0f * zz - xx - yy); basis[14] = {{SH_C3_5}}f * dz * (xx - yy);
    basis[15] = {{SH_C3_6}}f * dx * (xx - 3.0f * yy);
    const float* rest_ = (const float*)sh_rest.data;
