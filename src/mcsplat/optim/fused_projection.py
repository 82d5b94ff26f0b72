"""The Gaussians' update in one pass on the CPU: the projection's backward applies Adam.

The plain step walks every Gaussian's parameters three times after the compositing: the projection's backward reads
them and writes their gradients, autograd hands those on, then Adam reads parameters, gradients and moments and writes
them back. Here one SIMD kernel (fused_projection.cpp) takes 128 Gaussians at a time, 16 to a vector: the
projection's backward (render/project/cpu_simd_backward.cpp, the same C++) writes their gradient rows to the stack,
and Adam updates their rows of all six parameters at once, while they are in the cache; the gradients never reach
memory. The render leaves
the projection's share of the gradients to this update (render/project/deferred.py); what other terms gave the
parameters (--surface's) is in their `.grad` and joins here, and the opacities' gradient, which the compositing
gives, is read from theirs. The MCMC regularizers leave their gradients here too (deferred.regularizers_left_to_update)
and the kernel adds them: weight / count x exp(s) to the log-scales, x sigmoid'(o) to the opacity logits.

The result is the plain step's to the bit where at most one other term adds to a parameter the projection reads (the
regularizers; tests/training/test_fused_projection.py): the backward is the same C++ built with the same options, the
gradients sum as autograd sums two (the projection's share through exp for the log-scales, then the other term's),
and the Adam arithmetic is adam_cpu's, which is torch's fused CPU Adam's. Where more terms add up (--surface's render
outputs read the scales too) the order of the sum differs: the same to float32 rounding. Adam's
state stays in the torch.optim.Adam objects (checkpoints, row surgery and resume as before); the host counts the
step counters up and turns them into each parameter's two step constants, as adam_cpu's kernel does per launch.

The update applies where the plain step would run adam_cpu's kernel on exactly the model's six optimizers; anywhere
else (another optimizer, a projection that did not defer) it finishes the deferred gradients into `.grad` and steps
as usual. A projection that ran the Warp kernels (CUDA; the CPU's scalar kernels) gets the same update from
fused_projection_warp.py's kernel, to float32 rounding.
"""

from __future__ import annotations

import math
from contextlib import AbstractContextManager, nullcontext
from typing import Mapping

import numpy as np
import torch
import warp as wp

from .. import adam_cpu
from ..compute.cpp_snippets import read_snippet
from ..compute.cpu_target import kernel_flags
from ..compute.runtime import ensure_warp, flat_view, numpy_view, run_ranges
from ..compute.simd_lanes import LANES
from ..gaussians import PARAM_KEYS, GaussianModel
from ..render.project import cpu_simd, deferred
from ..render.project.warp_kernel import gradients_of
from . import fused_projection_warp
from .stepping import step_optimizers, together_in_one_launch

REST_MAX = 45  # floats in a Gaussian's rest SH row at degree 3, the highest the model stores
CHUNKS = 8  # chunks of LANES Gaussians a thread takes at once (fused_projection.cpp: about 50 KB of stack rows)

_SOURCE = read_snippet(__package__, "fused_projection.cpp", {
    "LANES": LANES, "CHUNKS": CHUNKS, "REST_MAX": REST_MAX, "TORCH_SCALAR_TAIL": adam_cpu.TORCH_SCALAR_TAIL,
    "BACKWARD": cpu_simd.backward_source(
        {"means": "scratch_means", "quats": "scratch_quats", "scales": "scratch_scales", "dc": "scratch_dc",
         "rest": "scratch_rest"}, out_first="chunk_first")})

# The projection backward's options (cpu_simd.py), so that its gradients are the plain kernel's to the bit; the Adam
# part turns contraction off itself.
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-mprefer-vector-width=512 -ffp-contract=fast")})

_floats = wp.array(dtype=wp.float32)


@wp.func_native(_SOURCE)
def _update_block(block: int, n: int, camera: _floats, width: int, height: int, sh_degree: int, antialiased: int,
                  means: _floats, quats: _floats, scales: _floats, sh_dc: _floats, sh_rest: _floats, dc_stride: int,
                  rest_stride: int, rest_shift: int, rest_count: int, colors: _floats, grad_means2d: _floats,
                  grad_conics: _floats, grad_depths: _floats, grad_colors: _floats, grad_compensations: _floats,
                  view_grad: int, out_view: _floats, tensors: wp.array(dtype=wp.int64), step_constants: _floats,
                  beta1: wp.float64, beta2: wp.float64, eps: wp.float64, opacities: _floats, regularized: int,
                  opacity_factor: float, scale_factor: float): ...


@wp.kernel
def projection_backward_adam(first_block: int, n: int, camera: _floats, width: int, height: int, sh_degree: int,
                             antialiased: int, means: _floats, quats: _floats, scales: _floats, sh_dc: _floats,
                             sh_rest: _floats, dc_stride: int, rest_stride: int, rest_shift: int, rest_count: int,
                             colors: _floats, grad_means2d: _floats, grad_conics: _floats, grad_depths: _floats,
                             grad_colors: _floats, grad_compensations: _floats, view_grad: int, out_view: _floats,
                             tensors: wp.array(dtype=wp.int64), step_constants: _floats, beta1: wp.float64,
                             beta2: wp.float64, eps: wp.float64, opacities: _floats, regularized: int,
                             opacity_factor: float, scale_factor: float):
    """One thread per block of CHUNKS x LANES Gaussians; each thread writes only its own Gaussians' rows."""
    _update_block(first_block + wp.tid(), n, camera, width, height, sh_degree, antialiased, means, quats, scales,
                  sh_dc, sh_rest, dc_stride, rest_stride, rest_shift, rest_count, colors, grad_means2d, grad_conics,
                  grad_depths, grad_colors, grad_compensations, view_grad, out_view, tensors, step_constants, beta1,
                  beta2, eps, opacities, regularized, opacity_factor, scale_factor)


KERNELS = [projection_backward_adam]
_NO_VIEW = torch.zeros(12, dtype=torch.float32)  # never written (the view gradient is off), never the camera's numbers


def _step_constants(steps: list[torch.Tensor], rates: list[float], beta1: float, beta2: float) -> np.ndarray:
    """Per parameter -lr / (1 - beta1^step) and sqrt(1 - beta2^step), each rounded to float32 from double as
    adam_cpu's kernel rounds them."""
    constants = []
    for step, rate in zip(steps, rates):
        count = float(step.numpy())
        bias1, bias2 = 1.0 - math.pow(beta1, count), 1.0 - math.pow(beta2, count)
        constants += [-(rate / bias1), math.sqrt(bias2)]
    return np.array(constants, dtype=np.float32)


def update(pending: deferred.DeferredBackward, params: list[torch.Tensor], states: list[dict], rates: list[float],
           beta1: float, beta2: float, eps: float) -> None:
    """One Adam step of the six parameters (PARAM_KEYS' order, `pending`'s the model's) with the projection's
    gradients from `pending` plus each `.grad`; `states` are their Adam states (made here when empty, as torch does
    on a first step), `rates` their learning rates. The `.grad`s are dropped."""
    ensure_warp()
    if not takes(pending, params):  # the kernel writes the rows of `pending`'s Gaussians into `params`
        raise ValueError(f"the fused update takes the deferred projection's own six parameters in PARAM_KEYS' order "
                         f"{PARAM_KEYS}, got shapes {[tuple(p.shape) for p in params]}")
    for param, state in zip(params, states):
        if not state:
            state.update(step=torch.zeros((), dtype=torch.float32), exp_avg=torch.zeros_like(param),
                         exp_avg_sq=torch.zeros_like(param))
    steps = [state["step"] for state in states]
    torch._foreach_add_(steps, 1)  # as torch's Adam does, before its step reads them
    table = np.array([t.data_ptr() if t is not None else 0 for param, state in zip(params, states)
                      for t in (param, state["exp_avg"], state["exp_avg_sq"], param.grad)], dtype=np.int64)
    n = pending.means.shape[0]
    dc_stride, rest_stride, rest_shift, rest_count = cpu_simd._sh_layout(pending.sh_dc, pending.sh_rest, False)
    no_view = _NO_VIEW  # the backward's view gradient is off; an array of its own stands for its output
    regularized = pending.regularizers is not None
    factors = [float(f) for f in pending.regularizers] if regularized else [0.0, 0.0]
    run_ranges(projection_backward_adam, -(-n // (CHUNKS * LANES)), pending.means.device, [
        n, flat_view(pending.camera), pending.width, pending.height, pending.sh_degree, int(pending.antialiased),
        *(flat_view(t) for t in (pending.means, pending.quats, pending.scales, pending.sh_dc, pending.sh_rest)),
        dc_stride, rest_stride, rest_shift, rest_count, flat_view(pending.colors),
        *(flat_view(t) for t in pending.upstream), 0, flat_view(no_view), numpy_view(table),
        numpy_view(_step_constants(steps, rates, beta1, beta2)), float(beta1), float(beta2), float(eps),
        flat_view(pending.opacities if regularized else no_view), int(regularized), *factors],
        min_per_thread=4096 // (CHUNKS * LANES))
    for param in params:
        param.grad = None


def takes(pending: deferred.DeferredBackward, params: list[torch.Tensor]) -> bool:
    """Whether `params` (PARAM_KEYS' order) are the tensors `pending`'s projection read, in the shapes the kernel
    walks (the rest SH row within its scratch row)."""
    n = pending.means.shape[0]
    shapes = [tuple(p.shape) for p in params]
    return (pending.means is params[0] and pending.quats is params[2] and pending.sh_dc is params[4]
            and pending.sh_rest is params[5] and tuple(pending.scales.shape) == (n, 3)
            and shapes[:5] == [(n, 3), (n, 3), (n, 4), (n,), (n, 1, 3)] and len(shapes[5]) == 3
            and shapes[5][0] == n and shapes[5][2] == 3 and 3 * shapes[5][1] <= REST_MAX)


def finish_gradients(pending: deferred.DeferredBackward, model: GaussianModel) -> None:
    """Add the deferred projection gradients (and the regularizers', where they were left too) to the model's
    `.grad`s, as autograd would have (where the fused update does not apply)."""
    g_means, g_quats, g_scales, g_dc, g_rest = gradients_of(pending)
    params = model.params
    extra = []
    if pending.regularizers is not None:  # theirs join the others' first, as the fused kernel sums them
        opacity_factor, scale_factor = pending.regularizers
        left = scale_factor * pending.scales
        params["log_scales"].grad = left if params["log_scales"].grad is None else params["log_scales"].grad + left
        extra = [("opacity_logits", opacity_factor * (1.0 - pending.opacities) * pending.opacities)]
    for key, grad in (("means", g_means), ("quats", g_quats), ("log_scales", g_scales * pending.scales),
                      ("sh0", g_dc), ("shN", g_rest), *extra):
        param = params[key]
        param.grad = grad if param.grad is None else param.grad + grad


class FusedProjectionAdam:
    """The Gaussians' update of a training step as one pass (see the module's docstring): `rendering(model)` around
    the render, `step(optimizers)` in place of optim.step_optimizers."""

    def __init__(self) -> None:
        self._model: GaussianModel | None = None
        self._deferral: deferred.Deferral | None = None
        self._rows = fused_projection_warp.GradientRows()  # the Warp kernel's, kept from step to step

    def rendering(self, model: GaussianModel) -> AbstractContextManager:
        params = model.params
        if any(params[key].dtype != torch.float32 for key in PARAM_KEYS):
            self._model, self._deferral = None, None
            return nullcontext()
        self._model = model
        self._deferral = deferred.Deferral(params["means"], params["quats"], params["log_scales"], params["sh0"],
                                           params["shN"], params["opacity_logits"])
        return deferred.deferring(self._deferral)

    def step(self, optimizers: Mapping[str, torch.optim.Optimizer]) -> None:
        model, deferral = self._model, self._deferral
        self._model = self._deferral = None
        pending = deferral.pending if deferral is not None else None
        if pending is None:
            step_optimizers(optimizers)
            return
        launch = together_in_one_launch(optimizers, model, cpu=pending.simd)
        if launch is None or not takes(pending, launch["params"]):
            finish_gradients(pending, model)
            step_optimizers(optimizers)
            return
        rest = {key: opt for key, opt in optimizers.items() if key not in PARAM_KEYS}
        if rest:
            step_optimizers(rest)
        if pending.simd:
            update(pending, **launch)
        else:
            fused_projection_warp.update(pending, self._rows, **launch)
