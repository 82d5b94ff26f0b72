{{PRELUDE}}
{{GEOMETRY}}

    // The colour, + 0.5 and clamped at 0, lane by lane (each Gaussian's coefficients are one row).
    const float* dc_ = (const float*)sh_dc.data;
    float* colors_ = (float*)out_colors.data;
    for (int l = 0; l < count; ++l) {
        const float* dc_row = dc_ + (first + l) * dc_stride;
        const float* rest_row = rest_ + (first + l) * rest_stride + 3 * rest_shift;
        float sum[3] = {basis[0][l] * dc_row[0], basis[0][l] * dc_row[1], basis[0][l] * dc_row[2]};
        for (int k = 1; k < basis_count; ++k) {
            const float weight = basis[k][l];
            for (int ch = 0; ch < 3; ++ch) sum[ch] += weight * rest_row[3 * (k - 1) + ch];
        }
        for (int ch = 0; ch < 3; ++ch) colors_[3 * (first + l) + ch] = sum[ch] + 0.5f > 0.0f ? sum[ch] + 0.5f : 0.0f;
    }
    vf opacity_row[1];
{{LOAD_OPACITY_ROW}}

    const vf opacity = opacity_row[0];
    const vf conic[3] = {c / det_safe, -b / det_safe, a / det_safe};
    // Mip-Splatting's 2D filter: the opacity shrinks by the ratio of the areas before and after the low-pass.
    const vf compensation = antialiased ? vsqrt(vmax((cov00 * cov11 - b * b) / det_safe, (vf)0.0f)) : (vf)1.0f;
    const vf mean2d[2] = {fx * p[0] / z_safe + cx, fy * p[1] / z_safe + cy};

    // Screen extent (no gradient): radius from the largest eigenvalue, the tiles it touches, the alpha box.
    const vf mid = 0.5f * (a + c);
    const vf lambda_max = mid + vsqrt(vmax(0.25f * (a - c) * (a - c) + b * b, (vf)0.1f));
    vf extent = 3.0f;
    vi valid = valid_conic;
    if (opacity_aware_radius) {
        // Beyond sqrt(2 ln(255 o)) sigma the alpha falls under 1/255 and the pixel is skipped anyway.
        extent = vmin(vsqrt(vmax(2.0f * log_lanes(vmax(255.0f * opacity, (vf)1.0f)), (vf)0.0f)), (vf)3.0f);
        valid &= 255.0f * opacity > 1.0f;
    }
    const vf radius = __builtin_elementwise_ceil(extent * vsqrt(vmax(lambda_max, (vf)0.0f)));
    const float tile = {{TILE_SIZE}}.0f;
    auto tile_of = [&](vf x, int limit, float shift) -> vf {
        return vmin(vmax(__builtin_elementwise_floor(x / tile) + shift, (vf)0.0f), (vf)(float)limit);
    };
    const vf lo_x = tile_of(mean2d[0] - radius, tiles_x, 0.0f), hi_x = tile_of(mean2d[0] + radius, tiles_x, 1.0f);
    const vf lo_y = tile_of(mean2d[1] - radius, tiles_y, 0.0f), hi_y = tile_of(mean2d[1] + radius, tiles_y, 1.0f);
    // Finite: |x| <= FLT_MAX (false for inf and NaN).
    const vi finite = ((vf)((vi)mean2d[0] & 0x7fffffff) <= 3.40282347e38f)
        & ((vf)((vi)mean2d[1] & 0x7fffffff) <= 3.40282347e38f);
    valid &= (radius > 0.0f) & (hi_x > lo_x) & (hi_y > lo_y) & finite;
    // Half-widths of the box outside which o exp(-d^T Q d / 2) < 1/255 (see project._alpha_extent).
    const vf k_box = vmax(2.0f * log_lanes(vmax(255.0f * opacity, (vf)1e-30f)), (vf)0.0f);
    const vi has_box = k_box > 0.0f;
    const vf box_x = select(has_box, vsqrt(k_box * vmax(a, (vf)0.0f)) * 1.001f + 0.01f, (vf)0.0f);
    const vf box_y = select(has_box, vsqrt(k_box * vmax(c, (vf)0.0f)) * 1.001f + 0.01f, (vf)0.0f);

    const vi kept_radius = valid & __builtin_convertvector(radius, vi);
    const vi kept_lo_x = valid & __builtin_convertvector(lo_x, vi);
    const vi kept_lo_y = valid & __builtin_convertvector(lo_y, vi);
    const vi kept_hi_x = valid & __builtin_convertvector(hi_x, vi);
    const vi kept_hi_y = valid & __builtin_convertvector(hi_y, vi);
{{STORE_MEANS2D}}
{{STORE_CONICS}}
{{STORE_DEPTHS}}
{{STORE_COMPENSATIONS}}
{{STORE_RADII}}
{{STORE_TILE_MIN}}
{{STORE_TILE_MAX}}
{{STORE_ALPHA_EXTENT}}
