{{VECTOR_TYPES}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    float* means_ = (float*)means.data;
    const float* quats_ = (const float*)quats.data;
    const float* log_scales_ = (const float*)log_scales.data;
    const float* logits_ = (const float*)opacity_logits.data;
{{SIMD_MATH}}
    // exp of arguments kept where 2^n is a normal float
    auto exp_kept = [&](vf x) -> vf {
        return exp_lanes(__builtin_elementwise_min(__builtin_elementwise_max(x, (vf)-87.0f), (vf)88.0f));
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
        vf s[3];
        for (int c = 0; c < 3; ++c) s[c] = exp_kept(log_s[c]);
        const vf* v = e;
        vf* result = shaped;
{{COVARIANCE}}
    }
    vf weight = (vf)factor;
    if (gated) {  // factor x sigmoid(-K (o - C)), o = sigmoid(logit)
        vf logit;
        for (int l = 0; l < {{LANES}}; ++l) logit[l] = logits_[first + (l < count ? l : count - 1)];
        const vf opacity = 1.0f / (1.0f + exp_kept(-logit));
        weight = factor * (1.0f / (1.0f + exp_kept(gate_k * (opacity - gate_center))));
    }
    for (int k = 0; k < 3; ++k) m[k] = m[k] + shaped[k] * weight;
{{STORE_M}}
