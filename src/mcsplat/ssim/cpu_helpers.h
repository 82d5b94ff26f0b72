
    const float taps[{{WINDOW}}] = {{TAP_LIST}};
    const int half = {{HALF_WINDOW}}, window = {{WINDOW}};
    const int w = width, h = height;
    const long plane = (long)w * h;
    const int first = (int)((long)part * h / parts), last = (int)((long)(part + 1) * h / parts);
    // Each output is summed in a register over the 11 taps (a fixed count, so the loop over k unrolls and the loop
    // over j vectorises), rather than added into `out` tap by tap: one store a value instead of eleven.
    auto blur_row = [&](const float* __restrict padded, float* __restrict out) {  // padded[0 .. w + 2 half) -> w
        for (int j = 0; j < w; ++j) {
            float sum = taps[0] * padded[j];
            for (int k = 1; k < {{WINDOW}}; ++k) sum += taps[k] * padded[j + k];
            out[j] = sum;
        }
    };
    // A sum in double over 8 lanes: a single running sum would keep the loop it sits in from being vectorised.
    auto sum_lanes = [](const float* values, int count) {
        double lanes[8] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        int j = 0;
        for (; j + 8 <= count; j += 8)
            for (int k = 0; k < 8; ++k) lanes[k] += values[j + k];
        double total = 0.0;
        for (; j < count; ++j) total += values[j];
        for (int k = 0; k < 8; ++k) total += lanes[k];
        return total;
    };
    // The rows of the window around `row` inside the image, blurred down the columns from the ring (maps of w);
    // rows outside the image are read from `zeros` (maps of w zeros), which adds nothing.
    auto blur_column = [&](const float* ring, const float* zeros, int maps, int row, float* __restrict out) {
        const float* rows[{{WINDOW}}];
        for (int k = 0; k < window; ++k) {
            const int source = row + k - half;
            rows[k] = source < 0 || source >= h ? zeros : ring + (long)(source % window) * maps * w;
        }
        for (int j = 0; j < maps * w; ++j) {
            float sum = 0.0f;
            for (int k = 0; k < {{WINDOW}}; ++k) sum += taps[k] * rows[k][j];
            out[j] = sum;
        }
    };
