
{{VECTOR_TYPES}}

    auto select = [](vi mask, vf a, vf b) -> vf { return (vf)(((vi)a & mask) | ((vi)b & ~mask)); };
    auto vmin = [](vf a, vf b) -> vf { return __builtin_elementwise_min(a, b); };
    auto vmax = [](vf a, vf b) -> vf { return __builtin_elementwise_max(a, b); };
    auto vsqrt = [](vf x) -> vf { return __builtin_elementwise_sqrt(x); };
    auto any_lane = [](vi mask) -> bool { return __builtin_reduce_or(mask) != 0; };
{{SIMD_MATH}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    const float* cam = (const float*)camera.data;
    const float W[3][3] = {{cam[0], cam[1], cam[2]}, {cam[3], cam[4], cam[5]}, {cam[6], cam[7], cam[8]}};
    const float t[3] = {cam[9], cam[10], cam[11]};
    const float centre[3] = {cam[12], cam[13], cam[14]};
    const float fx = cam[15], fy = cam[16], cx = cam[17], cy = cam[18];
    const float near_plane = cam[19], far_plane = cam[20], eps2d = cam[21];
    // Bounds of x/z and y/z for the Jacobian: the field of view widened by 30% on each side (3DGS, gsplat).
    const float tan_fovx = 0.5f * (float)width / fx, tan_fovy = 0.5f * (float)height / fy;
    const float lim_x_neg = cx / fx + 0.3f * tan_fovx, lim_x_pos = ((float)width - cx) / fx + 0.3f * tan_fovx;
    const float lim_y_neg = cy / fy + 0.3f * tan_fovy, lim_y_pos = ((float)height - cy) / fy + 0.3f * tan_fovy;
    const int basis_count = (sh_degree + 1) * (sh_degree + 1);

    // The chunk's Gaussians in lanes (spare lanes repeat the last one).
    vf mean[3], q_raw[4], s[3];
{{LOAD_MEAN}}
{{LOAD_S}}
{{LOAD_Q_RAW}}
