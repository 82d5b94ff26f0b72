
    const int* order_ = (const int*)order.data;
    const int* counts_ = (const int*)counts.data;
    int* offsets_ = (int*)offsets.data;
    long long slot = 0;
    for (int k = 0; k < n; ++k) {
        const int g = order_[k];
        offsets_[g] = (int)slot;
        slot += counts_[g];
    }
    ((long long*)total.data)[0] = slot;
