    // exp and log over the lanes of a vf (Cephes' expf and logf polynomials; relative error about 1e-7): a libm call
    // would stop a loop from vectorising. The kernels that read this define vf and vi first.
    // exp(x) for x where 2^round(x / ln 2) is a normal float (about [-87, 88]), by the 2^n exponent trick.
    auto exp_lanes = [](vf x) -> vf {
        vf fx = x * 1.44269504088896341f + 0.5f;
        vi n = __builtin_convertvector(fx, vi);
        n -= (vi)(__builtin_convertvector(n, vf) > fx) & 1;  // truncation -> floor for negative values
        vf nf = __builtin_convertvector(n, vf);
        x = x - nf * 0.693359375f + nf * 2.12194440e-4f;
        vf p = 1.9875691500e-4f;
        p = p * x + 1.3981999507e-3f;
        p = p * x + 8.3334519073e-3f;
        p = p * x + 4.1665795894e-2f;
        p = p * x + 1.6666665459e-1f;
        p = p * x + 5.0000001201e-1f;
        p = p * x * x + x + 1.0f;
        return p * (vf)((n + 127) << 23);
    };
    // Natural log of positive normal numbers (mantissa in [sqrt(1/2), sqrt(2)), a degree-9 polynomial).
    auto log_lanes = [](vf x) -> vf {
        vi bits = (vi)x;
        vi e = ((bits >> 23) & 0xff) - 126;
        vf m = (vf)((bits & 0x807fffff) | 0x3f000000);  // in [0.5, 1)
        vi small = m < 0.707106781186547524f;
        e += small;  // small is -1 where true
        m = (vf)(((vi)(m + m) & small) | ((vi)m & ~small)) - 1.0f;
        vf z = m * m;
        vf y = 7.0376836292e-2f;
        y = y * m - 1.1514610310e-1f;
        y = y * m + 1.1676998740e-1f;
        y = y * m - 1.2420140846e-1f;
        y = y * m + 1.4249322787e-1f;
        y = y * m - 1.6668057665e-1f;
        y = y * m + 2.0000714765e-1f;
        y = y * m - 2.4999993993e-1f;
        y = y * m + 3.3333331174e-1f;
        y = y * m * z;
        vf fe = __builtin_convertvector(e, vf);
        y += -2.12194440e-4f * fe;
        y += -0.5f * z;
        return m + y + 0.693359375f * fe;
    };
