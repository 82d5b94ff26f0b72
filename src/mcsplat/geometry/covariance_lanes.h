    {  // result = Sigma v = R S^2 R^T v over the lanes: q[4] the quaternions (normalised here), s[3] the scales
        vf norm = __builtin_elementwise_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        norm = __builtin_elementwise_max(norm, (vf)1e-12f);
        const vf w = q[0] / norm, x = q[1] / norm, y = q[2] / norm, z = q[3] / norm;
        const vf r[3][3] = {
            {1.0f - 2.0f * (y * y + z * z), 2.0f * (x * y - w * z), 2.0f * (x * z + w * y)},
            {2.0f * (x * y + w * z), 1.0f - 2.0f * (x * x + z * z), 2.0f * (y * z - w * x)},
            {2.0f * (x * z - w * y), 2.0f * (y * z + w * x), 1.0f - 2.0f * (x * x + y * y)}};
        vf local[3];  // R^T v scaled by s^2, then R of that
        for (int c = 0; c < 3; ++c) local[c] = (r[0][c] * v[0] + r[1][c] * v[1] + r[2][c] * v[2]) * s[c] * s[c];
        for (int k = 0; k < 3; ++k) result[k] = r[k][0] * local[0] + r[k][1] * local[1] + r[k][2] * local[2];
    }
