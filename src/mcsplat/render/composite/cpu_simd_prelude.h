
    typedef float vf __attribute__((ext_vector_type(16)));
    typedef int vi __attribute__((ext_vector_type(16)));
    typedef float vf8 __attribute__((ext_vector_type(8)));
    typedef float vf4 __attribute__((ext_vector_type(4)));
    const float alpha_min = {{ALPHA_MIN}}f, alpha_max = {{ALPHA_MAX}}f;
    const int PREFETCH_DISTANCE = {{PREFETCH_DISTANCE}};
    const float power_skip = {{POWER_SKIP}}f, transmittance_min = {{TRANSMITTANCE_MIN}}f;

    auto select = [](vi mask, vf a, vf b) -> vf { return (vf)(((vi)a & mask) | ((vi)b & ~mask)); };
    auto any_lane = [](vi mask) -> bool { return __builtin_reduce_or(mask) != 0; };
    auto all_lanes = [](vi mask) -> bool { return __builtin_reduce_and(mask) != 0; };
    // Sum of the 16 lanes in a fixed tree order (the result must not depend on the compiler's choices).
    auto lane_sum = [](vf v) -> float {
        vf8 a = v.lo + v.hi;
        vf4 b = a.lo + a.hi;
        return (b.x + b.z) + (b.y + b.w);
    };
    // exp_lanes (compute/simd_math.h) serves forward and backward alike: x lies in [power_skip, 0].
{{SIMD_MATH}}

    const int* range = (const int*)tile_ranges.data + 2 * tile;
    const int start = range[0], end = range[1];
    const int* ids = (const int*)gaussian_ids.data;
    const int* pair_masks_ = (const int*)pair_masks.data;
    const float* rows = (const float*)records.data;
    // The list's Gaussians lie anywhere in the records (and, backward, in the gradient rows): a record fetched
    // when its entry comes up costs a miss of the cache each time, so the entry PREFETCH_DISTANCE ahead is asked
    // for early (both cache lines a 40-byte row may straddle).
    auto prefetch_ahead = [&](int k, const float* gradient_rows) {
        if (k + PREFETCH_DISTANCE >= end) return;
        const int ahead = 10 * ids[k + PREFETCH_DISTANCE];
        __builtin_prefetch(rows + ahead);
        __builtin_prefetch(rows + ahead + 9);
        if (gradient_rows) {
            __builtin_prefetch(gradient_rows + ahead, 1);
            __builtin_prefetch(gradient_rows + ahead + 9, 1);
        }
    };
    const int tile_x0 = (tile % tiles_x) * {{TILE_SIZE}}, tile_y0 = (tile / tiles_x) * {{TILE_SIZE}};
    vf lane_dx, lane_dy;  // pixel-centre offsets of the 16 lanes inside a 4x4 block
    vi lane_x, lane_y;
    for (int l = 0; l < 16; ++l) {
        lane_x[l] = l % 4; lane_y[l] = l / 4;
        lane_dx[l] = (float)(l % 4) + 0.5f; lane_dy[l] = (float)(l / 4) + 0.5f;
    }
    int block_x0[16], block_y0[16];
    vi inside[16];  // lanes on image pixels (the last tiles may hang over the edge)
    for (int b = 0; b < 16; ++b) {
        block_x0[b] = tile_x0 + (b % 4) * 4;
        block_y0[b] = tile_y0 + (b / 4) * 4;
        inside[b] = ((lane_x + block_x0[b]) < width) & ((lane_y + block_y0[b]) < height);
    }
