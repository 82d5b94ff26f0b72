
    const int* tiles_ = (const int*)tiles.data;
    const long long* pairs_ = (const long long*)pairs.data;
    int* ids_ = (int*)gaussian_ids.data;
    int* masks_ = (int*)pair_masks.data;
    int* ranges_ = (int*)tile_ranges.data;
    for (int k = 0; k < total; ++k) {
        ids_[k] = (int)(pairs_[k] & 0xffffffffLL);
        masks_[k] = (int)(pairs_[k] >> 32);
    }
    int k = 0;
    for (int t = 0; t < num_tiles; ++t) {  // the pairs are sorted by tile; an empty tile's range is empty
        ranges_[2 * t] = k;
        while (k < total && tiles_[k] == t) ++k;
        ranges_[2 * t + 1] = k;
    }
