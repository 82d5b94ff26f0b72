    // One block of {{CHUNKS}} chunks of {{LANES}} Gaussians: the projection's backward, chunk by chunk, into gradient
    // rows kept on the stack, then Adam over the block's rows of each parameter (means, log_scales, quats,
    // opacity_logits, sh0, shN: PARAM_KEYS). A block's rows of a parameter are one run of memory: Adam streams
    // through six runs of its three arrays, long enough for the hardware's prefetch, where a chunk's were a few lines.
    constexpr int BLOCK = {{CHUNKS}} * {{LANES}};
    float scratch_means[3 * BLOCK], scratch_quats[4 * BLOCK], scratch_scales[3 * BLOCK];
    float scratch_dc[3 * BLOCK], scratch_rest[{{REST_MAX}} * BLOCK];
    const int chunk_first = BLOCK * block;  // the scratch rows start at the block's first Gaussian
    const int rows = n - chunk_first < BLOCK ? n - chunk_first : BLOCK;
    if (rows <= 0) return;
    for (int chunk = {{CHUNKS}} * block; chunk < {{CHUNKS}} * block + (rows + {{LANES}} - 1) / {{LANES}}; ++chunk) {
{{BACKWARD}}
    }

    // Per parameter: its tensor, exp_avg, exp_avg_sq and the gradient other terms gave it (0: none), as addresses;
    // -lr / (1 - beta1^step) and sqrt(1 - beta2^step) as float32 (the host reads the step counters).
    const long long* table = (const long long*)tensors.data;
    const float* constants = (const float*)step_constants.data;
    const float* scales_ = (const float*)scales.data;
    const float* opacities_ = (const float*)opacities.data;  // read only where `regularized`
    const float* fresh[6] = {scratch_means, scratch_scales, scratch_quats, nullptr, scratch_dc, scratch_rest};
    const int widths[6] = {3, 3, 4, 1, 3, rest_stride};
    const float weight = (float)(1.0 - beta1);
    const bool small_weight = __builtin_fabsf(weight) < 0.5f;
    const float coefficient = small_weight ? weight : weight - 1.0f;
    const float decay2 = (float)beta2, weight2 = (float)(1.0 - beta2), epsilon = (float)eps;
    float g[{{REST_MAX}} * BLOCK];  // one parameter's gradient rows of the block
    for (int t = 0; t < 6; ++t) {
        // torch's fused CPU Adam, element for element (optim/fused_projection.py): no contraction but the fmas
        // written out, the other form of v in torch's scalar loop over a tensor's last n % 8 elements.
        #pragma clang fp contract(off)
        float* __restrict param = (float*)table[4 * t];
        float* __restrict exp_avg = (float*)table[4 * t + 1];
        float* __restrict exp_avg_sq = (float*)table[4 * t + 2];
        const float* __restrict earlier = (const float*)table[4 * t + 3];
        const float* __restrict own = fresh[t];
        const float minus_step_size = constants[2 * t], bias2_sqrt = constants[2 * t + 1];
        const long long width = widths[t], total = (long long)n * width;
        const long long begin = (long long)chunk_first * width, count = (long long)rows * width;
        // The gradient as autograd sums it: the projection's (through exp for the log-scales), the regularizers'
        // where they were left here (their mean's backward times exp's or sigmoid's), plus the others'.
        if (own == nullptr) {  // the opacity logits: the compositing's, through sigmoid, comes in `earlier`
            for (long long j = 0; j < count; ++j) g[j] = earlier != nullptr ? earlier[begin + j] : 0.0f;
            if (regularized)
                for (long long j = 0; j < count; ++j) {
                    const float o = opacities_[begin + j];
                    g[j] = g[j] + opacity_factor * (1.0f - o) * o;  // torch's sigmoid_backward: (a (1 - o)) o
                }
        } else if (t == 1 && regularized) {  // the projection's share plus (the others' plus the regularizer's)
            for (long long j = 0; j < count; ++j) {
                const float s = scales_[begin + j], others = scale_factor * s;
                g[j] = own[j] * s + (earlier != nullptr ? earlier[begin + j] + others : others);
            }
        } else if (t == 1) {
            for (long long j = 0; j < count; ++j) g[j] = own[j] * scales_[begin + j];
        } else {
            for (long long j = 0; j < count; ++j) g[j] = own[j];
        }
        if (own != nullptr && earlier != nullptr && !(t == 1 && regularized))
            for (long long j = 0; j < count; ++j) g[j] = g[j] + earlier[begin + j];
        float* __restrict p_ = param + begin;
        float* __restrict m_ = exp_avg + begin;
        float* __restrict v_ = exp_avg_sq + begin;
        const long long vectors_end = total - total % {{TORCH_SCALAR_TAIL}};
        const long long split = vectors_end - begin < count ? (vectors_end > begin ? vectors_end - begin : 0) : count;
        for (long long j = 0; j < split; ++j) {  // where torch's vector loops run
            const float m = __builtin_fmaf(coefficient, g[j] - m_[j], small_weight ? m_[j] : g[j]);
            const float v = __builtin_fmaf(weight2 * g[j], g[j], v_[j] * decay2);
            m_[j] = m;
            v_[j] = v;
            p_[j] = p_[j] + (minus_step_size * m) / (__builtin_sqrtf(v) / bias2_sqrt + epsilon);
        }
        for (long long j = split; j < count; ++j) {  // torch's scalar loop
            const float m = __builtin_fmaf(coefficient, g[j] - m_[j], small_weight ? m_[j] : g[j]);
            const float v = __builtin_fmaf(v_[j], decay2, (weight2 * g[j]) * g[j]);
            m_[j] = m;
            v_[j] = v;
            p_[j] = p_[j] + (minus_step_size * m) / (__builtin_sqrtf(v) / bias2_sqrt + epsilon);
        }
    }
