{{PRELUDE}}

    vf transmittance[16], red[16], green[16], blue[16], depth[16];
    vi last[16], done[16];
{{MEDIAN_DECLARE}}
    int active = 0;  // blocks with a pixel still compositing
    for (int b = 0; b < 16; ++b) {
        transmittance[b] = 1.0f; red[b] = 0.0f; green[b] = 0.0f; blue[b] = 0.0f; depth[b] = 0.0f;
        last[b] = 0; done[b] = ~inside[b];
        if (!all_lanes(done[b])) active |= 1 << b;
    }
    unsigned char* contributed_ = (unsigned char*)contributed.data;  // a bool tensor
    for (int k = start; k < end && active; ++k) {
{{LIST_ENTRY}}
        bool composited = false;
        while (blocks) {
            const int b = __builtin_ctz(blocks);
            blocks &= blocks - 1;
{{EVALUATE_BLOCK}}

            vi use = passes & ~done[b];
            if (!any_lane(use)) continue;
            vf next_t = transmittance[b] * (1.0f - alpha);
            vi stop = use & (next_t < transmittance_min);
            done[b] |= stop;
            use &= ~stop;
            vf weight = select(use, alpha * transmittance[b], (vf)0.0f);
            red[b] += weight * row[6];
            green[b] += weight * row[7];
            blue[b] += weight * row[8];
            depth[b] += weight * row[9];
{{MEDIAN_UPDATE}}
            transmittance[b] = select(use, next_t, transmittance[b]);
            last[b] = (use & (k - start + 1)) | (~use & last[b]);
            composited = composited || any_lane(use);
            if (all_lanes(done[b])) active &= ~(1 << b);
        }
        if (composited) contributed_[g] = 1;
    }

    const float* bg = (const float*)background.data;
    float* rgb_out = (float*)out_rgb.data;
    float* t_out = (float*)out_transmittance.data;
    float* depth_out = (float*)out_depth.data;
    int* last_out = (int*)out_last.data;
    for (int b = 0; b < 16; ++b) {
        for (int l = 0; l < 16; ++l) {
            const int px = block_x0[b] + l % 4, py = block_y0[b] + l / 4;
            if (px >= width || py >= height) continue;
            const int pixel = py * width + px;
            const float t = transmittance[b][l];
            rgb_out[3 * pixel + 0] = red[b][l] + t * bg[0];
            rgb_out[3 * pixel + 1] = green[b][l] + t * bg[1];
            rgb_out[3 * pixel + 2] = blue[b][l] + t * bg[2];
            t_out[pixel] = t;
            depth_out[pixel] = depth[b][l];
            last_out[pixel] = last[b][l];
{{MEDIAN_STORE}}
        }
    }
