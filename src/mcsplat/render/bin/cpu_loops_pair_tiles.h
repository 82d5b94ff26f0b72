
    const int* tile_min_ = (const int*)tile_min.data;
    const int* tile_max_ = (const int*)tile_max.data;
    const float* means2d_ = (const float*)means2d.data;
    const float* extent_ = (const float*)alpha_extent.data;
    auto clamped = [](float x) -> float { return x < -1.0e9f ? -1.0e9f : (x > 1.0e9f ? 1.0e9f : x); };
    auto pair_tiles = [&](int i, int* span, int* rect) {
        rect[0] = tile_min_[2 * i]; rect[1] = tile_max_[2 * i];
        rect[2] = tile_min_[2 * i + 1]; rect[3] = tile_max_[2 * i + 1];
        if (!use_masks) return;
        for (int axis = 0; axis < 2; ++axis) {
            const float mean = means2d_[2 * i + axis], extent = extent_[2 * i + axis];
            const int first = (int)__builtin_ceilf(clamped(mean - extent - 0.5f));
            const int last = (int)__builtin_floorf(clamped(mean + extent - 0.5f));
            span[2 * axis] = first; span[2 * axis + 1] = last;
            int* lo = rect + 2 * axis;
            int* hi = rect + 2 * axis + 1;
            if (last < first || last < 0) { *hi = *lo; continue; }
            const int a = (first > 0 ? first : 0) / {{TILE_SIZE}}, b = last / {{TILE_SIZE}} + 1;
            if (a > *lo) *lo = a;
            if (b < *hi) *hi = b;
        }
    };
