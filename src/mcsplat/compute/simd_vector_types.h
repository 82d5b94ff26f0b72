
    typedef float vf __attribute__((ext_vector_type({{LANES}})));
    typedef int vi __attribute__((ext_vector_type({{LANES}})));
    typedef float vf_u __attribute__((ext_vector_type({{LANES}}), aligned(4)));
    typedef int vi_u __attribute__((ext_vector_type({{LANES}}), aligned(4)));
