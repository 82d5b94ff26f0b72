    // Rows [first, last) of the records: mean x, y, conic a, b, c, opacity, r, g, b, depth (RECORD_WIDTH).
    const long long first = (long long){{ROWS}} * block;
    const long long last = first + {{ROWS}} < n ? first + {{ROWS}} : n;
    const float* __restrict means2d_ = (const float*)means2d.data;
    const float* __restrict conics_ = (const float*)conics.data;
    const float* __restrict opacities_ = (const float*)opacities.data;
    const float* __restrict colors_ = (const float*)colors.data;
    const float* __restrict depths_ = (const float*)depths.data;
    float* __restrict out = (float*)records.data;
    for (long long i = first; i < last; ++i) {
        float* row = out + 10 * i;
        row[0] = means2d_[2 * i];
        row[1] = means2d_[2 * i + 1];
        row[2] = conics_[3 * i];
        row[3] = conics_[3 * i + 1];
        row[4] = conics_[3 * i + 2];
        row[5] = opacities_[i];
        row[6] = colors_[3 * i];
        row[7] = colors_[3 * i + 1];
        row[8] = colors_[3 * i + 2];
        row[9] = depths_[i];
    }
