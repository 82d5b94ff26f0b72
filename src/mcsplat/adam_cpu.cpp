
    const long long* addresses = (const long long*)tensors.data;  // per tensor: param, grad, exp_avg, exp_avg_sq, step
    const long long* sizes_ = (const long long*)sizes.data;
    const double* rates_ = (const double*)rates.data;
    long long blocks = 0;
    for (int t = 0; t < count; ++t) blocks += (sizes_[t] + {{BLOCK_LESS_ONE}}) / {{BLOCK}};
    const long long first = blocks * part / parts, last = blocks * (part + 1) / parts;  // this part's blocks
    const float weight = (float)(1.0 - beta1);
    const bool small_weight = __builtin_fabsf(weight) < 0.5f;
    const float coefficient = small_weight ? weight : weight - 1.0f;
    const float decay2 = (float)beta2, weight2 = (float)(1.0 - beta2), epsilon = (float)eps;
    long long start = 0;  // the tensor's first block in the launch's count
    for (int t = 0; t < count; ++t) {
        const long long n = sizes_[t], own = (n + {{BLOCK_LESS_ONE}}) / {{BLOCK}};
        const long long a = (first > start ? first : start) - start;
        const long long b = (last < start + own ? last : start + own) - start;
        start += own;
        if (a >= b) continue;
        float* __restrict param = (float*)addresses[5 * t];
        const float* __restrict grad = (const float*)addresses[5 * t + 1];
        float* __restrict exp_avg = (float*)addresses[5 * t + 2];
        float* __restrict exp_avg_sq = (float*)addresses[5 * t + 3];
        const double step = (double)*(const float*)addresses[5 * t + 4];
        const double bias1 = 1.0 - __builtin_pow(beta1, step), bias2 = 1.0 - __builtin_pow(beta2, step);
        const float minus_step_size = (float)(-(rates_[t] / bias1)), bias2_sqrt = (float)__builtin_sqrt(bias2);
        const long long end = b * {{BLOCK}} < n ? b * {{BLOCK}} : n, vectors_end = n - n % {{TORCH_SCALAR_TAIL}};
        long long i = a * {{BLOCK}};
        for (; i < end && i < vectors_end; ++i) {  // where torch's vector loops run
            const float g = grad[i], m_old = exp_avg[i];
            const float m = __builtin_fmaf(coefficient, g - m_old, small_weight ? m_old : g);
            const float v = __builtin_fmaf(weight2 * g, g, exp_avg_sq[i] * decay2);
            exp_avg[i] = m;
            exp_avg_sq[i] = v;
            param[i] = param[i] + (minus_step_size * m) / (__builtin_sqrtf(v) / bias2_sqrt + epsilon);
        }
        for (; i < end; ++i) {  // torch's scalar loop
            const float g = grad[i], m_old = exp_avg[i];
            const float m = __builtin_fmaf(coefficient, g - m_old, small_weight ? m_old : g);
            const float v = __builtin_fmaf(exp_avg_sq[i], decay2, (weight2 * g) * g);
            exp_avg[i] = m;
            exp_avg_sq[i] = v;
            param[i] = param[i] + (minus_step_size * m) / (__builtin_sqrtf(v) / bias2_sqrt + epsilon);
        }
    }
