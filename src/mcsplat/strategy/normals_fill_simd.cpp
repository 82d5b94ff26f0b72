{{VECTOR_TYPES}}

    const int first = {{LANES}} * chunk;
    const int count = n - first < {{LANES}} ? n - first : {{LANES}};
    if (count <= 0) return;
    float* out_ = (float*)out.data;
{{NORMALS}}
{{STORE_ETA}}
