        prefetch_ahead(k, {{GRADIENT_ROWS}});
        int blocks = pair_masks_[k] & active;
        if (!blocks) continue;
        const int g = ids[k];
        const float* row = rows + 10 * g;
        const float mx = row[0], my = row[1], ca = row[2], cb = row[3], cc = row[4], opacity = row[5];
