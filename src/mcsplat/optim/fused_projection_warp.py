"""The fused update's Warp kernel, for the projection's Warp kernels (CUDA; on the CPU the scalar kernels the tests
run): one thread per Gaussian runs the projection's backward (render/project/warp_kernel.py's
`backward_of_gaussian`, the plain backward's own function) into gradient rows, then Adam over that Gaussian's rows of
the six parameters, in one launch instead of the backward's, autograd's and the six optimizers'.

The gradient rows are buffers kept from step to step (sized to the model, made again when it changes size), each
thread zeroing its own rows first. Adam is torch's (the lerp form of the first moment, the bias corrections in float64
from the step counters, which stay on the device and are counted up before the launch, as torch's fused Adam does);
the result is the plain update's to float32 rounding (tests/training/test_fused_projection.py), not to the bit: the
arithmetic of torch's CUDA kernel is not reproduced.
"""


import functools

import torch
import warp as wp

from ..compute.runtime import run_ranges, warp_scalar, warp_view
from ..render.project import deferred
from ..render.project.warp_kernel import projection_kernels


@functools.lru_cache(maxsize=None)
def fused_kernel(dtype):
    """The fused kernel for scalar type wp.float32 or wp.float64."""
    vec2 = wp.types.vector(2, dtype)
    vec3 = wp.types.vector(3, dtype)
    vec4 = wp.types.vector(4, dtype)
    flat = wp.array(dtype=dtype)
    steps = wp.array(dtype=wp.float32)  # torch's fused Adam counts in float32
    zero = dtype(0.0)
    backward = projection_kernels(dtype)[1]
    backward_of_gaussian, camera_of = backward.of_gaussian, backward.camera_of

    @wp.func
    def adam_at(param: flat, exp_avg: flat, exp_avg_sq: flat, j: int, g: dtype, step: steps, rate: wp.float64,
                beta1: wp.float64, beta2: wp.float64, eps: dtype):
        count = wp.float64(step[0])
        bias1 = wp.float64(1.0) - wp.pow(beta1, count)
        bias2 = wp.float64(1.0) - wp.pow(beta2, count)
        minus_step_size = dtype(-rate / bias1)
        bias2_sqrt = dtype(wp.sqrt(bias2))
        m = exp_avg[j] + dtype(wp.float64(1.0) - beta1) * (g - exp_avg[j])
        v = exp_avg_sq[j] * dtype(beta2) + dtype(wp.float64(1.0) - beta2) * g * g
        exp_avg[j] = m
        exp_avg_sq[j] = v
        param[j] = param[j] + minus_step_size * m / (wp.sqrt(v) / bias2_sqrt + eps)

    @wp.func
    def earlier_at(earlier: flat, j: int) -> dtype:
        """The gradient other terms gave (an empty array: none)."""
        if earlier.shape[0] == 0:
            return zero
        return earlier[j]

    @wp.kernel(module="unique")
    def project_backward_adam(
        offset: int, camera: flat, width: int, height: int, sh_degree: int, antialiased: int,
        means: wp.array(dtype=vec3), quats: wp.array(dtype=vec4), scales: wp.array(dtype=vec3),
        sh_dc: wp.array2d(dtype=vec3), sh_rest: wp.array2d(dtype=vec3), rest_count: int,
        grad_means2d: wp.array(dtype=vec2), grad_conics: wp.array(dtype=vec3), grad_depths: wp.array(dtype=dtype),
        grad_colors: wp.array(dtype=vec3), grad_compensations: wp.array(dtype=dtype),
        g_means: wp.array(dtype=vec3), g_quats: wp.array(dtype=vec4), g_scales: wp.array(dtype=vec3),
        g_dc: wp.array2d(dtype=vec3), g_rest: wp.array2d(dtype=vec3), no_view: wp.array2d(dtype=dtype),
        # per parameter, in PARAM_KEYS' order (means, log_scales, quats, opacity_logits, sh0, shN): the parameter,
        # its moments and step counter flat, the gradient other terms gave (empty: none), its learning rate
        p0: flat, m0: flat, v0: flat, s0: steps, e0: flat, r0: wp.float64,
        p1: flat, m1: flat, v1: flat, s1: steps, e1: flat, r1: wp.float64,
        p2: flat, m2: flat, v2: flat, s2: steps, e2: flat, r2: wp.float64,
        p3: flat, m3: flat, v3: flat, s3: steps, e3: flat, r3: wp.float64,
        p4: flat, m4: flat, v4: flat, s4: steps, e4: flat, r4: wp.float64,
        p5: flat, m5: flat, v5: flat, s5: steps, e5: flat, r5: wp.float64,
        beta1: wp.float64, beta2: wp.float64, eps: dtype,
    ):
        i = offset + wp.tid()
        rotation, translation, camera_center, fx, fy, cx, cy, near, far, eps2d = camera_of(camera)
        g_means[i] = vec3(zero, zero, zero)
        g_scales[i] = vec3(zero, zero, zero)
        g_quats[i] = vec4(zero, zero, zero, zero)
        g_dc[i, 0] = vec3(zero, zero, zero)
        for k in range(rest_count):
            g_rest[i, k] = vec3(zero, zero, zero)
        backward_of_gaussian(
            i, rotation, translation, camera_center, fx, fy, cx, cy, width, height, near, far, eps2d, sh_degree,
            antialiased, means, quats, scales, sh_dc, sh_rest, 0, grad_means2d, grad_conics, grad_depths,
            grad_colors, grad_compensations, g_means, g_quats, g_scales, g_dc, g_rest, 0, no_view)
        for k in range(3):
            j = 3 * i + k
            adam_at(p0, m0, v0, j, g_means[i][k] + earlier_at(e0, j), s0, r0, beta1, beta2, eps)
            # the log-scales: through exp, as autograd hands it on
            adam_at(p1, m1, v1, j, g_scales[i][k] * scales[i][k] + earlier_at(e1, j), s1, r1, beta1, beta2, eps)
            adam_at(p4, m4, v4, j, g_dc[i, 0][k] + earlier_at(e4, j), s4, r4, beta1, beta2, eps)
        for k in range(4):
            adam_at(p2, m2, v2, 4 * i + k, g_quats[i][k] + earlier_at(e2, 4 * i + k), s2, r2, beta1, beta2, eps)
        adam_at(p3, m3, v3, i, e3[i], s3, r3, beta1, beta2, eps)  # the opacities: the compositing's gradient
        for r in range(rest_count):
            for k in range(3):
                j = 3 * (rest_count * i + r) + k
                adam_at(p5, m5, v5, j, g_rest[i, r][k] + earlier_at(e5, j), s5, r5, beta1, beta2, eps)

    return project_backward_adam


class GradientRows:
    """The kernel's gradient buffers, kept from step to step and made again when the model changes size."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._buffers: list[torch.Tensor] = []

    def for_model(self, means: torch.Tensor, sh_rest: torch.Tensor) -> list[torch.Tensor]:
        key = (means.shape[0], sh_rest.shape[1], means.dtype, means.device)
        if key != self._key:
            n, like = means.shape[0], means
            self._buffers = [like.new_empty(n, 3), like.new_empty(n, 4), like.new_empty(n, 3),
                             like.new_empty(n, 1, 3), like.new_empty(n, sh_rest.shape[1], 3), like.new_empty(1, 12)]
            self._key = key
        return self._buffers


def update(pending: deferred.DeferredBackward, rows: GradientRows, params: list[torch.Tensor], states: list[dict],
           rates: list[float], beta1: float, beta2: float, eps: float) -> None:
    """One Adam step of the six parameters (PARAM_KEYS' order, `pending`'s the model's) with the projection's
    gradients from `pending` plus each `.grad`, in one launch; the `.grad`s are dropped."""
    for param, state in zip(params, states):
        if not state:  # torch's fused Adam's state: its counter a float32 tensor on the parameter's device
            state.update(step=torch.zeros((), dtype=torch.float32, device=param.device),
                         exp_avg=torch.zeros_like(param), exp_avg_sq=torch.zeros_like(param))
    torch._foreach_add_([state["step"] for state in states], 1)
    scalar = warp_scalar(pending.means.dtype)
    vec = functools.partial(_vectors, scalar=scalar)
    g_means, g_quats, g_scales, g_dc, g_rest, no_view = rows.for_model(pending.means, pending.sh_rest)
    per_parameter = []
    for param, state, rate in zip(params, states, rates):
        earlier = param.grad if param.grad is not None else param.new_empty(0)
        per_parameter += [warp_view(t.reshape(-1)) for t in (param, state["exp_avg"], state["exp_avg_sq"],
                                                              state["step"], earlier)] + [wp.float64(rate)]
    upstream = pending.upstream
    run_ranges(fused_kernel(scalar), pending.means.shape[0], pending.means.device, [
        warp_view(pending.camera), pending.width, pending.height, pending.sh_degree, int(pending.antialiased),
        vec(pending.means, 3), vec(pending.quats, 4), vec(pending.scales, 3), vec(pending.sh_dc, 3),
        vec(pending.sh_rest, 3), pending.sh_rest.shape[1],
        vec(upstream[0], 2), vec(upstream[1], 3), warp_view(upstream[2]), vec(upstream[3], 3),
        warp_view(upstream[4]), vec(g_means, 3), vec(g_quats, 4), vec(g_scales, 3), vec(g_dc, 3), vec(g_rest, 3),
        warp_view(no_view), *per_parameter, wp.float64(beta1), wp.float64(beta2), scalar(eps)])
    for param in params:
        param.grad = None


def _vectors(tensor: torch.Tensor, length: int, scalar):
    return warp_view(tensor, wp.types.vector(length, scalar))
