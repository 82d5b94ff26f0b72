{{PAIR_TILES}}

    int* counts_ = (int*)counts.data;
    for (int i = begin; i < end; ++i) {
        int span[4], rect[4];
        pair_tiles(i, span, rect);
        const int w = rect[1] - rect[0], h = rect[3] - rect[2];
        counts_[i] = (w > 0 ? w : 0) * (h > 0 ? h : 0);
    }
