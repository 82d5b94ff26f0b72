    // The pairs sorted by tile and split in one counting sort: each tile's pairs counted (in tile_ranges' second
    // column), their starts summed, then every pair, in the order written (front to back within a tile: stable),
    // written as its Gaussian and block mask at its tile's next place.
    const int* tiles_ = (const int*)tiles.data;
    const long long* pairs_ = (const long long*)pairs.data;
    int* ids_ = (int*)gaussian_ids.data;
    int* masks_ = (int*)pair_masks.data;
    int* ranges_ = (int*)tile_ranges.data;
    for (int t = 0; t < num_tiles; ++t) ranges_[2 * t + 1] = 0;
    for (int k = 0; k < total; ++k) ++ranges_[2 * tiles_[k] + 1];
    int start = 0;
    for (int t = 0; t < num_tiles; ++t) {
        const int count = ranges_[2 * t + 1];
        ranges_[2 * t] = start;
        ranges_[2 * t + 1] = start;  // the tile's next place; its end once every pair is in
        start += count;
    }
    for (int k = 0; k < total; ++k) {
        const int at = ranges_[2 * tiles_[k] + 1]++;
        ids_[at] = (int)(pairs_[k] & 0xffffffffLL);
        masks_[at] = (int)(pairs_[k] >> 32);
    }
