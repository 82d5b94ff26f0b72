    // Items [first, last): where the Gaussian was visible (radius > 0), add the norm of its 2D position gradient in
    // NDC units (x times width / 2, y times height / 2) and count the view.
    const long long first = (long long){{ROWS}} * block;
    const long long last = first + {{ROWS}} < n ? first + {{ROWS}} : n;
    const float* __restrict grad_ = (const float*)grad.data;
    const int* __restrict radii_ = (const int*)radii.data;
    float* __restrict total_ = (float*)total.data;
    int* __restrict views_ = (int*)views.data;
    for (long long i = first; i < last; ++i) {
        const float x = grad_[2 * i] * half_width, y = grad_[2 * i + 1] * half_height;
        const bool visible = radii_[i] > 0;
        total_[i] = total_[i] + (visible ? __builtin_sqrtf(x * x + y * y) : 0.0f);
        views_[i] = views_[i] + (visible ? 1 : 0);
    }
