    // The Gaussians front to back, then each one's first slot. Keys: a visible Gaussian's depth as its float's bits
    // (positive floats order like their bit patterns), 0 for the others. A stable LSD radix sort on three digits of
    // 11, 11 and 10 bits (the last holds the sign bit, 0 here; 2,048 counts a digit, all three counted in one read)
    // scatters between the two halves of the room; a digit every key shares is skipped. Then offsets[g] = the pairs
    // of the Gaussians in front of g.
    const float* depths_ = (const float*)depths.data;
    const int* radii_ = (const int*)radii.data;
    const int* counts_ = (const int*)counts.data;
    unsigned int* keys_ = (unsigned int*)keys.data;  // 2n
    int* order_ = (int*)order.data;  // 2n
    int* offsets_ = (int*)offsets.data;
    int digit_counts[3][2048];  // 24 KB of stack
    for (int d = 0; d < 3; ++d)
        for (int b = 0; b < 2048; ++b) digit_counts[d][b] = 0;
    for (int i = 0; i < n; ++i) {
        unsigned int key = 0;
        if (radii_[i] > 0) __builtin_memcpy(&key, depths_ + i, 4);
        keys_[i] = key;
        order_[i] = i;
        ++digit_counts[0][key & 2047];
        ++digit_counts[1][(key >> 11) & 2047];
        ++digit_counts[2][key >> 22];
    }
    long long half = 0;  // where the items lie: 0 or n
    for (int d = 0; d < 3; ++d) {
        int* digit = digit_counts[d];
        bool shared = false;
        int start = 0;
        for (int b = 0; b < 2048; ++b) {
            const int c = digit[b];
            shared = shared || c == n;
            digit[b] = start;
            start += c;
        }
        if (shared) continue;
        const unsigned int* key_in = keys_ + half;
        const int* order_in = order_ + half;
        unsigned int* key_out = keys_ + (n - half);
        int* order_out = order_ + (n - half);
        const int shift = 11 * d;
        for (int i = 0; i < n; ++i) {
            const unsigned int key = key_in[i];
            const int at = digit[(key >> shift) & 2047]++;
            key_out[at] = key;
            order_out[at] = order_in[i];
        }
        half = n - half;
    }
    const int* sorted = order_ + half;
    long long slot = 0;
    for (int k = 0; k < n; ++k) {
        const int g = sorted[k];
        offsets_[g] = (int)slot;
        slot += counts_[g];
    }
    ((long long*)total.data)[0] = slot;
