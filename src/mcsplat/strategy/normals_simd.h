    // Three standard normals for each of the chunk's Gaussians (lanes), from the draw's key and the Gaussian's index
    // alone: SplitMix64 of (key, 2 i) and (key, 2 i + 1) gives four 24-bit uniforms, Box-Muller makes them two pairs
    // of normals, of which three are kept. A counter, not a stream: the same numbers on any number of threads.
    typedef unsigned long long vu64 __attribute__((ext_vector_type({{LANES}})));
    typedef unsigned int vu32 __attribute__((ext_vector_type({{LANES}})));
    auto mix = [](vu64 z) -> vu64 {
        z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
        z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
        return z ^ (z >> 31);
    };
    // cos and sin of 2 pi t for t in [-1/2, 1/2): quarter turns taken out, then Cephes' sinf and cosf polynomials.
    auto turn_lanes = [](vf t, vf* cosine, vf* sine) {
        const vf quarter = __builtin_elementwise_roundeven(t * 4.0f);
        const vi k = __builtin_convertvector(quarter, vi) & 3;
        const vf x = (t - quarter * 0.25f) * 6.28318530717958648f;  // in [-pi/4, pi/4]
        const vf x2 = x * x;
        const vf s = ((-1.9515295891e-4f * x2 + 8.3321608736e-3f) * x2 - 1.6666654611e-1f) * x2 * x + x;
        const vf c = ((2.443315711809948e-5f * x2 - 1.388731625493765e-3f) * x2 + 4.166664568298827e-2f) * x2 * x2
                     - 0.5f * x2 + 1.0f;
        const vi odd = (k & 1) != 0, flip_c = (k == 1) | (k == 2), flip_s = (k == 2) | (k == 3);
        vf cc = (vf)(((vi)s & odd) | ((vi)c & ~odd)), ss = (vf)(((vi)c & odd) | ((vi)s & ~odd));
        *cosine = (vf)((vi)cc ^ (flip_c & (vi)(vf)-0.0f));
        *sine = (vf)((vi)ss ^ (flip_s & (vi)(vf)-0.0f));
    };
    vf eta[3];
    {
        vu64 index;
        for (int l = 0; l < {{LANES}}; ++l) index[l] = (unsigned long long)(first + (l < count ? l : count - 1));
        const unsigned long long golden = 0x9E3779B97F4A7C15ULL, seed = ((const unsigned long long*)key.data)[0];
        const vu64 h0 = mix(seed + (2 * index + 1) * golden), h1 = mix(seed + (2 * index + 2) * golden);
        const float unit = 5.9604644775390625e-8f;  // 2^-24
        auto uniform = [&](vu64 h, int shift) -> vf {  // (0, 1]: 24 bits and a half (1 where float32 rounds up)
            return (__builtin_convertvector(__builtin_convertvector((h >> shift) & 0xFFFFFFULL, vu32), vf) + 0.5f)
                   * unit;
        };
        const vf r0 = __builtin_elementwise_sqrt(-2.0f * log_lanes(uniform(h0, 40)));
        const vf r1 = __builtin_elementwise_sqrt(-2.0f * log_lanes(uniform(h1, 40)));
        vf c0, s0, c1, s1;
        turn_lanes(uniform(h0, 8) - 0.5f, &c0, &s0);
        turn_lanes(uniform(h1, 8) - 0.5f, &c1, &s1);
        eta[0] = r0 * c0;
        eta[1] = r0 * s0;
        eta[2] = r1 * c1;
    }
