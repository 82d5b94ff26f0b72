{{PRELUDE}}

    const float* bg = (const float*)background.data;
    const float* t_final = (const float*)final_transmittance.data;
    const int* last_in = (const int*)last_contributor.data;
    const float* rgb_in = (const float*)out_rgb.data;
    const float* depth_in = (const float*)out_depth.data;
    const float* g_rgb = (const float*)grad_rgb.data;
    const float* g_alpha = (const float*)grad_alpha.data;
    const float* g_depth = (const float*)grad_depth.data;
    float* grads_ = (float*)grads.data;

    // Per block: the upstream gradients, R (see the module docstring), the walk's state T and S, and the last
    // contributor of each lane; lanes off the image have last = 0 and take no part.
    vf gr[16], gg[16], gb[16], gd[16], rest[16], transmittance[16], prefix[16];
    vi last[16];
    int block_end[16];  // largest last contributor of the block
    int active = 0;
    for (int b = 0; b < 16; ++b) {
        block_end[b] = 0;
        for (int l = 0; l < 16; ++l) {
            const int px = block_x0[b] + l % 4, py = block_y0[b] + l / 4;
            if (px >= width || py >= height) {
                gr[b][l] = 0.0f; gg[b][l] = 0.0f; gb[b][l] = 0.0f; gd[b][l] = 0.0f; rest[b][l] = 0.0f;
                last[b][l] = 0;
                continue;
            }
            const int pixel = py * width + px;
            const float t = t_final[pixel];
            const float r = g_rgb[3 * pixel], g = g_rgb[3 * pixel + 1], bl = g_rgb[3 * pixel + 2];
            const float bg_term = bg[0] * r + bg[1] * g + bg[2] * bl;
            const float total = (rgb_in[3 * pixel] - t * bg[0]) * r + (rgb_in[3 * pixel + 1] - t * bg[1]) * g
                                + (rgb_in[3 * pixel + 2] - t * bg[2]) * bl + depth_in[pixel] * g_depth[pixel];
            gr[b][l] = r; gg[b][l] = g; gb[b][l] = bl; gd[b][l] = g_depth[pixel];
            rest[b][l] = total - t * (g_alpha[pixel] - bg_term);
            last[b][l] = last_in[pixel];
            if (last_in[pixel] > block_end[b]) block_end[b] = last_in[pixel];
        }
        transmittance[b] = 1.0f; prefix[b] = 0.0f;
        if (block_end[b] > 0) active |= 1 << b;
    }

    for (int k = start; k < end && active; ++k) {
{{LIST_ENTRY}}
        const float cr = row[6], cg = row[7], cbl = row[8], z = row[9];
        const int index = k - start;
        vf sum_mx = 0.0f, sum_my = 0.0f, sum_ca = 0.0f, sum_cb = 0.0f, sum_cc = 0.0f, sum_op = 0.0f;
        vf sum_r = 0.0f, sum_g = 0.0f, sum_b = 0.0f, sum_z = 0.0f;
        bool touched = false;
        while (blocks) {
            const int b = __builtin_ctz(blocks);
            blocks &= blocks - 1;
            if (index + 1 >= block_end[b]) active &= ~(1 << b);  // this entry is the block's last one to visit
{{EVALUATE_BLOCK}}

            vi use = passes & (last[b] > index);
            if (!any_lane(use)) continue;
            touched = true;
            vf t = transmittance[b];
            vf weight = select(use, alpha * t, (vf)0.0f);
            sum_r += weight * gr[b];
            sum_g += weight * gg[b];
            sum_b += weight * gb[b];
            sum_z += weight * gd[b];
            vf h = cr * gr[b] + cg * gg[b] + cbl * gb[b] + z * gd[b];
            vf one_minus_alpha = 1.0f - alpha;
            prefix[b] += weight * h;
            transmittance[b] = select(use, t * one_minus_alpha, t);
            // Clamped alphas (raw alpha above 0.99) no longer depend on opacity or position.
            vi free_alpha = use & (raw_alpha <= alpha_max);
            vf dl_dalpha = select(free_alpha, t * h - (rest[b] - prefix[b]) / one_minus_alpha, (vf)0.0f);
            sum_op += gauss * dl_dalpha;
            vf dl_dpower = raw_alpha * dl_dalpha;
            sum_mx -= dl_dpower * (ca * dx + cb * dy);
            sum_my -= dl_dpower * (cb * dx + cc * dy);
            sum_ca -= 0.5f * dl_dpower * dx * dx;
            sum_cb -= dl_dpower * dx * dy;
            sum_cc -= 0.5f * dl_dpower * dy * dy;
        }
        if (!touched) continue;
        float* out = grads_ + 10 * g;
        out[0] += lane_sum(sum_mx); out[1] += lane_sum(sum_my);
        out[2] += lane_sum(sum_ca); out[3] += lane_sum(sum_cb); out[4] += lane_sum(sum_cc);
        out[5] += lane_sum(sum_op);
        out[6] += lane_sum(sum_r); out[7] += lane_sum(sum_g); out[8] += lane_sum(sum_b);
        out[9] += lane_sum(sum_z);
    }
