{{HELPERS}}

    const float* x = (const float*)image.data;
    const float* y = (const float*)target.data;
    float* partial = (float*)partials.data;
    double* sums = (double*)row_sums.data;
    double* l1 = (double*)l1_sums.data;
    const int stride = w + 2 * half;
    // This part's room in `scratch` (forward_scratch_floats): a 4K image's ring (845 KB) is more than some
    // platforms give a thread's stack, and torch's allocation fails with a clear error where malloc's would crash.
    float* ring = (float*)scratch.data + (long)part * scratch_floats;
    float* padded = ring + window * 5 * w;
    float* stat = padded + 5 * stride;
    float* zeros = stat + 6 * w;
    for (int j = 0; j < 5 * w; ++j) zeros[j] = 0.0f;
    for (int s = 0; s < 5; ++s)
        for (int j = 0; j < half; ++j) padded[s * stride + j] = padded[s * stride + half + w + j] = 0.0f;
    for (int row = first; row < last; ++row) {
        sums[row] = 0.0;
        const float* xr = x + (long)row * w * 3;
        const float* yr = y + (long)row * w * 3;
        for (int j = 0; j < 3 * w; ++j) stat[j] = fabsf(xr[j] - yr[j]);
        l1[row] = sum_lanes(stat, 3 * w);  // the L1 loss's share of the row, read while the pixels are at hand
    }
    for (int c = 0; c < 3; ++c) {
        int next = first - half < 0 ? 0 : first - half;  // the next row to blur along
        for (int row = first; row < last; ++row) {
            const int need = row + half < h ? row + half : h - 1;
            for (; next <= need; ++next) {
                const float* xr = x + (long)next * w * 3;
                const float* yr = y + (long)next * w * 3;
                float* p = padded + half;
                for (int j = 0; j < w; ++j) {
                    const float xv = xr[3 * j + c], yv = yr[3 * j + c];
                    p[j] = xv; p[stride + j] = yv; p[2 * stride + j] = xv * xv;
                    p[3 * stride + j] = yv * yv; p[4 * stride + j] = xv * yv;
                }
                float* slot = ring + (long)(next % window) * 5 * w;
                for (int s = 0; s < 5; ++s) blur_row(padded + s * stride, slot + s * w);
            }
            blur_column(ring, zeros, 5, row, stat);
            float* d_mu = partial + (0 * 3 + c) * plane + (long)row * w;
            float* d_xx = partial + (1 * 3 + c) * plane + (long)row * w;
            float* d_xy = partial + (2 * 3 + c) * plane + (long)row * w;
            float* similarity = stat + 5 * w;
            for (int j = 0; j < w; ++j) {
                const float mx = stat[j], my = stat[w + j];
                const float var_x = stat[2 * w + j] - mx * mx, var_y = stat[3 * w + j] - my * my;
                const float cov = stat[4 * w + j] - mx * my;
                const float a = 2.0f * mx * my + {{C1}}f, b = 2.0f * cov + {{C2}}f;
                const float cc = mx * mx + my * my + {{C1}}f, d = var_x + var_y + {{C2}}f;
                const float inv = 1.0f / (cc * d);
                const float s = a * b * inv;
                similarity[j] = s;
                d_mu[j] = 2.0f * my * (b - a) * inv - 2.0f * s * mx / cc + 2.0f * s * mx / d;
                d_xx[j] = -s / d;
                d_xy[j] = 2.0f * a * inv;
            }
            sums[row] += sum_lanes(similarity, w);
        }
    }
