{{HELPERS}}

    const float* in = (const float*)partials.data;
    const float* x = (const float*)image.data;
    const float* y = (const float*)target.data;
    float* grad = (float*)grad_image.data;
    const int stride = w + 2 * half;
    float* ring = (float*)scratch.data + (long)part * scratch_floats;  // backward_scratch_floats
    float* padded = ring + window * 3 * w;
    float* b = padded + stride;
    float* zeros = b + 3 * w;
    for (int j = 0; j < 3 * w; ++j) zeros[j] = 0.0f;
    for (int j = 0; j < half; ++j) padded[j] = padded[half + w + j] = 0.0f;
    for (int c = 0; c < 3; ++c) {
        int next = first - half < 0 ? 0 : first - half;
        for (int row = first; row < last; ++row) {
            const int need = row + half < h ? row + half : h - 1;
            for (; next <= need; ++next) {
                float* slot = ring + (long)(next % window) * 3 * w;
                for (int q = 0; q < 3; ++q) {
                    const float* source = in + (q * 3 + c) * plane + (long)next * w;
                    for (int j = 0; j < w; ++j) padded[half + j] = source[j];
                    blur_row(padded, slot + q * w);
                }
            }
            blur_column(ring, zeros, 3, row, b);
            const float* xr = x + (long)row * w * 3;
            const float* yr = y + (long)row * w * 3;
            float* g = grad + (long)row * w * 3;
            for (int j = 0; j < w; ++j) {
                const float xv = xr[3 * j + c], yv = yr[3 * j + c];
                const float sign = xv > yv ? 1.0f : xv < yv ? -1.0f : 0.0f;  // |x - y|'s, 0 where they are equal
                g[3 * j + c] = scale * (b[j] + 2.0f * xv * b[w + j] + yv * b[2 * w + j]) + l1_scale * sign;
            }
        }
    }
