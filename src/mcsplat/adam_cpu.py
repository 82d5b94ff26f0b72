"""torch's fused Adam for float32 tensors on the CPU: every tensor of a step in one launch of one C++ loop.

torch.optim.Adam(fused=True) runs one operator per optimizer (and two profiler records around each step and
zero_grad); a training step has six. Here one Warp launch walks all the tensors, each element read once (parameter,
gradient, both moments) and written once (parameter, moments), with the arithmetic of torch's fused CPU kernel
(aten/src/ATen/native/cpu/FusedAdamKernel.cpp for float32, no weight decay, amsgrad or maximize) as torch's x86
build compiles it, so that the result is the same to the bit:

    bias1 = 1 - beta1^step, bias2 = 1 - beta2^step, step_size = lr / bias1        (in double, as torch)
    m = fma(w, g - m, m)         w = float(1 - beta1) below 0.5 (torch's lerp; else fma(w - 1, g - m, g))
    v = fma(c g, g, v beta2)     c = float(1 - beta2); the last n % 8 elements of a tensor: fma(v, beta2, (c g) g)
    p = p + (float(-step_size) m) / (sqrt(v) / float(sqrt(bias2)) + float(eps))

The two forms of v are where GCC contracted torch's `v * beta2 + c * g * g` into a fused multiply-add: its vector
loops (16 wide, then 8 wide over the remainder) one way, its scalar loop over the last n % 8 the other (measured
against torch 2.13's AVX-512 and AVX2 kernels, ATEN_CPU_CAPABILITY; its DEFAULT kernels contract nothing and keep
torch's own Adam: `matches_torch`). tests/training/test_adam_cpu.py compares the two bit for bit.

The state stays torch's (optim.py keeps torch.optim.Adam objects: state_dict and checkpoints as before); the caller
counts the step counters up first, as torch does, and the kernel reads them from their tensors (no host read). Each
thread takes a range of 16-element blocks over all the tensors, and an element's arithmetic depends only on its
place in its tensor (the module is built without contraction, each fma written out), so the result does not depend
on the threads.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from .compute.cpp_snippets import read_snippet
from .compute.cpu_target import kernel_flags
from .compute.runtime import cpu_threads, ensure_warp, numpy_view, run_ranges

BLOCK = 16  # elements a thread's range is counted in (one AVX-512 vector, a cache line)
TORCH_SCALAR_TAIL = 8  # torch's scalar loop takes a tensor's last n % 8 elements
ELEMENTS_PER_THREAD = 1 << 16  # fewer and a second thread costs more than it saves

# One part's blocks of the step, in C++ (adam_cpu.cpp).
_STEP = read_snippet(__package__, "adam_cpu.cpp", {
    "BLOCK": BLOCK, "BLOCK_LESS_ONE": BLOCK - 1, "TORCH_SCALAR_TAIL": TORCH_SCALAR_TAIL})

# No contraction: a * b + c stays two roundings unless an fma is written out. (Warp calls the compiler's front end,
# where errno is off: the square root vectorises.)
wp.set_module_options({"cpu_compiler_flags": kernel_flags("-ffp-contract=off")})

_addresses = wp.array(dtype=wp.int64)


@wp.func_native(_STEP)
def _adam_part(part: int, parts: int, count: int, tensors: _addresses, sizes: _addresses,
               rates: wp.array(dtype=wp.float64), beta1: wp.float64, beta2: wp.float64, eps: wp.float64): ...


@wp.kernel
def adam_step_cpu(offset: int, parts: int, count: int, tensors: _addresses, sizes: _addresses,
                  rates: wp.array(dtype=wp.float64), beta1: wp.float64, beta2: wp.float64, eps: wp.float64):
    _adam_part(offset + wp.tid(), parts, count, tensors, sizes, rates, beta1, beta2, eps)


KERNELS = [adam_step_cpu]


def matches_torch() -> bool:
    """Whether torch's CPU kernels are those the arithmetic above reproduces (x86 with AVX-512 or AVX2)."""
    return torch.backends.cpu.get_cpu_capability() in ("AVX512", "AVX2")


def applies(param: torch.Tensor, state: dict) -> bool:
    """Whether a parameter, its gradient (if it has one) and its Adam state are what the kernel takes: contiguous
    float32 on the CPU, the state's moments alike and its step counter a float32 number (torch's fused Adam's)."""
    grad = param.grad
    tensors = [param] + ([grad] if grad is not None else []) + [
        state[k] for k in ("exp_avg", "exp_avg_sq") if k in state]
    step = state.get("step")
    return (all(t.device.type == "cpu" and t.dtype == torch.float32 and t.is_contiguous() and not t.is_sparse
                and t.shape == param.shape for t in tensors)
            and (step is None or (step.dtype == torch.float32 and step.device.type == "cpu" and step.dim() == 0)))


def adam_step(params: list[torch.Tensor], exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
              steps: list[torch.Tensor], rates: list[float], beta1: float, beta2: float, eps: float) -> None:
    """One Adam step of every parameter (its `.grad`), in place: the step counters are counted up first, then one
    launch updates the parameters and moments (each tensor with its own learning rate in `rates`)."""
    if not params:
        return
    ensure_warp()
    torch._foreach_add_(steps, 1)  # as torch's Adam does, before its kernel reads them
    table = np.array([t.data_ptr() for row in zip(params, [p.grad for p in params], exp_avgs, exp_avg_sqs, steps)
                      for t in row], dtype=np.int64)
    sizes = np.array([p.numel() for p in params], dtype=np.int64)
    parts = max(1, min(cpu_threads(), int(sizes.sum()) // ELEMENTS_PER_THREAD))
    run_ranges(adam_step_cpu, parts, torch.device("cpu"), [
        parts, len(params), numpy_view(table), numpy_view(sizes), numpy_view(np.array(rates, dtype=np.float64)),
        float(beta1), float(beta2), float(eps)], 1)
