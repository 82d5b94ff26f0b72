{{VECTOR_TYPES}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    float* means_ = (float*)means.data;
    const float* quats_ = (const float*)quats.data;
    const float* log_scales_ = (const float*)log_scales.data;
    const float* logits_ = (const float*)opacity_logits.data;
    // exp(x) by Cephes' expf polynomial and the 2^n exponent trick (relative error about 1e-7), x kept where 2^n is a
    // normal float: a libm call would stop the loop from vectorising.
    auto exp_lanes = [](vf x) -> vf {
        x = __builtin_elementwise_min(__builtin_elementwise_max(x, (vf)-87.0f), (vf)88.0f);
        vf fx = x * 1.44269504088896341f + 0.5f;
        vi k = __builtin_convertvector(fx, vi);
        k -= (vi)(__builtin_convertvector(k, vf) > fx) & 1;  // truncation -> floor for negative values
        vf kf = __builtin_convertvector(k, vf);
        x = x - kf * 0.693359375f + kf * 2.12194440e-4f;
        vf p = 1.9875691500e-4f;
        p = p * x + 1.3981999507e-3f;
        p = p * x + 8.3334519073e-3f;
        p = p * x + 4.1665795894e-2f;
        p = p * x + 1.6666665459e-1f;
        p = p * x + 5.0000001201e-1f;
        p = p * x * x + x + 1.0f;
        return p * (vf)((k + 127) << 23);
    };
{{NORMALS}}
    vf m[3];
{{LOAD_M}}
    const vf* e = eta;
    vf shaped[3] = {e[0], e[1], e[2]};
    if (covariance) {  // Sigma eta = R S^2 R^T eta, as geometry/covariance_simd.cpp
        vf q[4], log_s[3];
{{LOAD_Q}}
{{LOAD_S}}
        vf norm = __builtin_elementwise_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        norm = __builtin_elementwise_max(norm, (vf)1e-12f);
        const vf w = q[0] / norm, x = q[1] / norm, y = q[2] / norm, z = q[3] / norm;
        const vf r[3][3] = {
            {1.0f - 2.0f * (y * y + z * z), 2.0f * (x * y - w * z), 2.0f * (x * z + w * y)},
            {2.0f * (x * y + w * z), 1.0f - 2.0f * (x * x + z * z), 2.0f * (y * z - w * x)},
            {2.0f * (x * z - w * y), 2.0f * (y * z + w * x), 1.0f - 2.0f * (x * x + y * y)}};
        vf local[3];
        for (int c = 0; c < 3; ++c) {
            const vf s = exp_lanes(log_s[c]);
            local[c] = (r[0][c] * e[0] + r[1][c] * e[1] + r[2][c] * e[2]) * s * s;
        }
        for (int k = 0; k < 3; ++k) shaped[k] = r[k][0] * local[0] + r[k][1] * local[1] + r[k][2] * local[2];
    }
    vf weight = (vf)factor;
    if (gated) {  // factor x sigmoid(-K (o - C)), o = sigmoid(logit)
        vf logit;
        for (int l = 0; l < {{LANES}}; ++l) logit[l] = logits_[first + (l < count ? l : count - 1)];
        const vf opacity = 1.0f / (1.0f + exp_lanes(-logit));
        weight = factor * (1.0f / (1.0f + exp_lanes(gate_k * (opacity - gate_center))));
    }
    for (int k = 0; k < 3; ++k) m[k] = m[k] + shaped[k] * weight;
{{STORE_M}}
