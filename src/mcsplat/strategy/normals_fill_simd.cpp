{{VECTOR_TYPES}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    float* out_ = (float*)out.data;
{{SIMD_MATH}}
{{NORMALS}}
{{STORE_ETA}}
