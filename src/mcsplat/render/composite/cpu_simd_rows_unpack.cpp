    // Rows [first, last): the workers' gradient rows summed in worker order (as `a + b + c` sums them), then written
    // to the five gradients by column (RECORD_WIDTH's order); the workers' rows are zeroed behind.
    const long long first = (long long){{ROWS}} * block;
    const long long last = first + {{ROWS}} < n ? first + {{ROWS}} : n;
    const long long* buffers_ = (const long long*)buffers.data;
    float* __restrict means2d_ = (float*)grad_means2d.data;
    float* __restrict conics_ = (float*)grad_conics.data;
    float* __restrict opacities_ = (float*)grad_opacities.data;
    float* __restrict colors_ = (float*)grad_colors.data;
    float* __restrict depths_ = (float*)grad_depths.data;
    for (long long i = first; i < last; ++i) {
        float row[10];
        float* own = (float*)buffers_[0] + 10 * i;
        for (int c = 0; c < 10; ++c) row[c] = own[c];
        for (int c = 0; c < 10; ++c) own[c] = 0.0f;  // left zeroed for the next backward
        for (int w = 1; w < workers; ++w) {
            float* other = (float*)buffers_[w] + 10 * i;
            for (int c = 0; c < 10; ++c) row[c] = row[c] + other[c];
            for (int c = 0; c < 10; ++c) other[c] = 0.0f;
        }
        means2d_[2 * i] = row[0];
        means2d_[2 * i + 1] = row[1];
        conics_[3 * i] = row[2];
        conics_[3 * i + 1] = row[3];
        conics_[3 * i + 2] = row[4];
        opacities_[i] = row[5];
        colors_[3 * i] = row[6];
        colors_[3 * i + 1] = row[7];
        colors_[3 * i + 2] = row[8];
        depths_[i] = row[9];
    }
