{{PAIR_TILES}}

    const int* offsets_ = (const int*)offsets.data;
    int* tiles_ = (int*)tiles.data;
    long long* pairs_ = (long long*)pairs.data;
    for (int i = begin; i < end; ++i) {
        int span[4], rect[4];
        pair_tiles(i, span, rect);
        int slot = offsets_[i];
        for (int ty = rect[2]; ty < rect[3]; ++ty) {
            // The rows of 4x4 blocks of tile row ty that the span reaches, as a column of 4-bit groups.
            int column = 0xffff;
            if (use_masks) {
                const int fy = span[2] - ty * {{TILE_SIZE}}, ly = span[3] - ty * {{TILE_SIZE}};
                const int bfy = (fy > 0 ? fy : 0) / {{BLOCK_SIZE}};
                const int bly = (ly < {{TILE_LAST}} ? ly : {{TILE_LAST}}) / {{BLOCK_SIZE}};
                column = ((1 << ({{BLOCK_SIZE}} * (bly + 1))) - (1 << ({{BLOCK_SIZE}} * bfy))) / 15;
            }
            for (int tx = rect[0]; tx < rect[1]; ++tx) {
                int mask = {{ALL_BLOCKS}};
                if (use_masks) {
                    const int fx = span[0] - tx * {{TILE_SIZE}}, lx = span[1] - tx * {{TILE_SIZE}};
                    const int bfx = (fx > 0 ? fx : 0) / {{BLOCK_SIZE}};
                    const int blx = (lx < {{TILE_LAST}} ? lx : {{TILE_LAST}}) / {{BLOCK_SIZE}};
                    mask = ((1 << (blx + 1)) - (1 << bfx)) * column;  // the row of blocks, in every row of the column
                }
                tiles_[slot] = ty * tiles_x + tx;
                pairs_[slot] = ((long long)mask << 32) | (long long)i;
                ++slot;
            }
        }
    }
