    vi median[16];
    for (int b = 0; b < 16; ++b) median[b] = -1;
    const float median_transmittance = {{MEDIAN_TRANSMITTANCE}}f;
    int* median_out = (int*)out_median.data;
