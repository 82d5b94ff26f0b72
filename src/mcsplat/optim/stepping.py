"""The Adam step of a training step's optimizers: on the CPU the model's six in one launch of adam_cpu's kernel
(torch's fused Adam's result to the bit, on torch's own state), any other optimizer by its own step()."""

from __future__ import annotations

from typing import Mapping

import torch
from torch.optim import optimizer as torch_optimizer

from .. import adam_cpu
from ..gaussians import PARAM_KEYS, GaussianModel

Optimizers = Mapping[str, torch.optim.Optimizer]


def step_optimizers(optimizers: Optimizers) -> None:
    """Each optimizer's Adam step, then its gradients dropped (zero_grad(set_to_none=True)). On the CPU the
    parameters of make_optimizers' Adams step together in one launch of adam_cpu's kernel (one per distinct betas
    and eps), with the result of their own step(); any other optimizer steps itself."""
    launches: dict[tuple[float, float, float], dict[str, list]] = {}
    together = [opt for opt in optimizers.values() if _steps_together(opt)]
    for opt in optimizers.values():
        if not any(opt is t for t in together):
            opt.step()
            opt.zero_grad(set_to_none=True)
    for opt in together:
        for group in opt.param_groups:
            launch = launches.setdefault((*group["betas"], group["eps"]), {
                "params": [], "exp_avgs": [], "exp_avg_sqs": [], "steps": [], "rates": []})
            for param in group["params"]:
                if param.grad is None:  # as torch: no gradient, no step (nor state)
                    continue
                state = opt.state[param]
                if not state:  # torch's lazy initialisation (a fused Adam's counter: a float32 tensor)
                    state.update(step=torch.zeros((), dtype=torch.float32), exp_avg=torch.zeros_like(param),
                                 exp_avg_sq=torch.zeros_like(param))
                for key, value in (("params", param), ("exp_avgs", state["exp_avg"]),
                                   ("exp_avg_sqs", state["exp_avg_sq"]), ("steps", state["step"]),
                                   ("rates", group["lr"])):
                    launch[key].append(value)
    for (beta1, beta2, eps), tensors in launches.items():
        adam_cpu.adam_step(**tensors, beta1=beta1, beta2=beta2, eps=eps)
    for opt in together:
        for group in opt.param_groups:
            for param in group["params"]:
                param.grad = None


def _plain_adam(opt: torch.optim.Optimizer) -> bool:
    """A torch.optim.Adam(fused=True) without hooks or the options a hand-written Adam step does not take."""
    if type(opt) is not torch.optim.Adam:
        return False
    hooks = (opt._optimizer_step_pre_hooks, opt._optimizer_step_post_hooks,
             torch_optimizer._global_optimizer_pre_hooks, torch_optimizer._global_optimizer_post_hooks)
    if any(hooks) or getattr(opt, "grad_scale", None) is not None or getattr(opt, "found_inf", None) is not None:
        return False
    return not any(not group.get("fused") or group["amsgrad"] or group["weight_decay"] or group["maximize"]
                   or group.get("decoupled_weight_decay") or group["capturable"] or group["differentiable"]
                   or isinstance(group["lr"], torch.Tensor) for group in opt.param_groups)


def _steps_together(opt: torch.optim.Optimizer) -> bool:
    """Whether adam_cpu's kernel gives `opt.step()`'s result: a plain Adam (above), its parameters (those with a
    gradient) and their state float32 on the CPU, and torch's CPU kernels those the kernel reproduces."""
    if not adam_cpu.matches_torch() or not _plain_adam(opt):
        return False
    return all(adam_cpu.applies(p, opt.state.get(p, {}))
               for group in opt.param_groups for p in group["params"] if p.grad is not None)


def _state_fits(param: torch.Tensor, state: dict) -> bool:
    """The parameter's `.grad` (if any) and Adam state in its dtype, shape and device, contiguous; the step counter a
    float32 number there (torch's fused Adam's)."""
    tensors = [param] + ([param.grad] if param.grad is not None else []) + [
        state[k] for k in ("exp_avg", "exp_avg_sq") if k in state]
    step = state.get("step")
    return (all(t.dtype == param.dtype and t.device == param.device and t.is_contiguous() and not t.is_sparse
                and t.shape == param.shape for t in tensors)
            and (step is None or (step.dtype == torch.float32 and step.device == param.device and step.dim() == 0)))


def together_in_one_launch(optimizers: Optimizers, model: GaussianModel, cpu: bool = True) -> dict | None:
    """The model's six parameters as one fused launch takes them (params, states, rates, beta1, beta2, eps): each
    key's optimizer a plain Adam (`cpu`: one step_optimizers gives adam_cpu's launch) holding that parameter alone,
    with the same betas and eps; their Adam state, and any `.grad` they hold, in the parameter's dtype, shape and
    device (`cpu`: float32 on the CPU). The opacities need their gradient (torch steps no parameter without one; the
    projection's five get theirs from the fused pass). None otherwise."""
    if any(key not in optimizers for key in PARAM_KEYS) or model.params["opacity_logits"].grad is None:
        return None
    launch: dict = {"params": [], "states": [], "rates": []}
    settings = set()
    for key in PARAM_KEYS:
        opt, param = optimizers[key], model.params[key]
        if (not (_steps_together(opt) if cpu else _plain_adam(opt)) or len(opt.param_groups) != 1
                or len(opt.param_groups[0]["params"]) != 1):
            return None
        group = opt.param_groups[0]
        state = opt.state.get(param, {})
        if group["params"][0] is not param or not (adam_cpu.applies if cpu else _state_fits)(param, state):
            return None
        settings.add((*group["betas"], group["eps"]))
        launch["params"].append(param)
        launch["states"].append(opt.state[param])  # made here when empty: torch's state, filled by the update
        launch["rates"].append(float(group["lr"]))
    if len(settings) != 1:
        return None
    (beta1, beta2, eps), = settings
    return {**launch, "beta1": beta1, "beta2": beta2, "eps": eps}

