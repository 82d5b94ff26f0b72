{{VECTOR_TYPES}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    const float* quats_ = (const float*)quats.data;
    const float* scales_ = (const float*)scales.data;
    const float* vectors_ = (const float*)vectors.data;
    float* out_ = (float*)out.data;
    vf q[4], s[3], v[3];
{{LOAD_Q}}
{{LOAD_S}}
{{LOAD_V}}

    vf result[3];
{{COVARIANCE}}
{{STORE_OUT}}
