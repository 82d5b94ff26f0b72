"""One Adam per parameter, the position learning-rate schedule, and row surgery that keeps them in step.

Adam with eps 1e-15 and betas (0.9, 0.999); learning rates per attribute; the position learning rate decays
log-linearly from 1.6e-4 R to 1.6e-6 R (R the scene radius): docs/method.md, "Optimizer and schedules". The official
code uses one Adam with one param group per attribute; one Adam per attribute (as gsplat does) is the same update and
lets each be rebuilt on its own.

Row surgery: densification and relocation add, copy and remove Gaussians. The helpers below change every parameter
of the model and the matching Adam state together:

- `append_rows`   concatenate new rows (their Adam moments start at zero);
- `copy_rows`     overwrite rows with other rows' values, in place (Adam state untouched);
- `set_rows`      write given values into rows of some parameters, in place (Adam state untouched);
- `remove_rows`   drop the rows of a mask from parameters and Adam state;
- `zero_moments`  zero the Adam moments of some rows (the step counter is untouched).

Appending and removing replace the Parameter objects (the model's and the optimizer's reference together; their
`.grad` is dropped). The optimizers stay plain torch.optim.Adam, so their state_dict()/load_state_dict() round trip
works as usual for checkpoints, as long as the model has the checkpoint's size when they are built.

`step_optimizers` (stepping.py) takes every optimizer's step: on the CPU in one launch over all their tensors
(adam_cpu.py: torch's fused Adam's arithmetic to the bit, on torch's own state), elsewhere each optimizer's own. A
training step's `ParameterUpdate` (update.py) wraps it; on the CPU the projection's backward applies it
(fused_projection.py). Both keep Adam's state in the torch.optim.Adam objects, so that row surgery, checkpoints and
resume do not know which ran.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Mapping

import torch

from ..gaussians import PARAM_KEYS, GaussianModel
from .stepping import step_optimizers
from .update import ParameterUpdate, PlainUpdate, training_kernels, update_for

__all__ = ["OptimConfig", "make_optimizers", "means_lr_at", "set_means_lr", "rates_on_device", "portable_state_dict",
           "step_optimizers", "training_kernels",
           "ParameterUpdate", "PlainUpdate", "update_for", "append_rows", "copy_rows", "set_rows", "remove_rows",
           "zero_moments"]

Optimizers = Mapping[str, torch.optim.Optimizer]


@dataclass(frozen=True)
class OptimConfig:
    """Learning rates of 3DGS (docs/method.md, "Optimizer and schedules"); the two position rates are multiplied by
    the scene radius."""

    means_lr: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    sh0_lr: float = 2.5e-3
    shN_lr: float = 2.5e-3 / 20
    opacity_lr: float = 0.05
    scales_lr: float = 5e-3
    quats_lr: float = 1e-3
    eps: float = 1e-15
    betas: tuple[float, float] = (0.9, 0.999)

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name.endswith("_lr") or f.name == "means_lr_final":
                value = getattr(self, f.name)
                if not (math.isfinite(value) and value >= 0):
                    raise ValueError(f"{f.name} must be a finite number >= 0, got {value}")
        if self.means_lr > 0 and not self.means_lr_final > 0:
            raise ValueError(f"means_lr_final must be > 0 for the log-linear decay, got {self.means_lr_final}")
        if not (self.eps >= 0 and math.isfinite(self.eps)):
            raise ValueError(f"eps must be a finite number >= 0, got {self.eps}")
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))  # frozen: normalised while made
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise ValueError(f"betas must be two numbers in [0, 1), got {self.betas}")

    def learning_rates(self, scene_radius: float) -> dict[str, float]:
        """Initial learning rate per parameter key."""
        return {"means": self.means_lr * scene_radius, "log_scales": self.scales_lr, "quats": self.quats_lr,
                "opacity_logits": self.opacity_lr, "sh0": self.sh0_lr, "shN": self.shN_lr}


def _check_radius(scene_radius: float) -> None:
    if not (scene_radius > 0 and math.isfinite(scene_radius)):
        raise ValueError(f"scene_radius must be a positive number, got {scene_radius}")


def make_optimizers(model: GaussianModel, config: OptimConfig, scene_radius: float) -> dict[str, torch.optim.Adam]:
    """One Adam per parameter key of `model.params`, with the learning rates of `config`.

    torch's fused Adam (one kernel per parameter, the same update) takes a third of the time of the default
    for-loop implementation on the CPU."""
    _check_radius(scene_radius)
    rates = config.learning_rates(scene_radius)
    return {key: torch.optim.Adam([model.params[key]], lr=rates[key], eps=config.eps, betas=config.betas, fused=True)
            for key in PARAM_KEYS}


def means_lr_at(step: int, max_steps: int, config: OptimConfig, scene_radius: float) -> float:
    """Position learning rate at `step`: log-linear from means_lr R (step 0) to means_lr_final R (step >= max_steps).

    This is 3DGS's get_expon_lr_func without delay and gsplat's ExponentialLR with
    gamma = 0.01^(1/max_steps). The official loop evaluates it at its 1-based iteration number before the step;
    gsplat's noise reads the rate after its scheduler step, i.e. at 0-based step + 1. The caller picks the step.
    """
    _check_radius(scene_radius)
    if max_steps <= 0:
        raise ValueError(f"max_steps must be positive, got {max_steps}")
    if config.means_lr == 0:
        return 0.0
    t = min(max(step / max_steps, 0.0), 1.0)
    log_lr = (1.0 - t) * math.log(config.means_lr) + t * math.log(config.means_lr_final)
    return math.exp(log_lr) * scene_radius


def set_means_lr(optimizers: Optimizers, lr: float) -> None:
    """Set the learning rate of the position optimizer (in place where it is a tensor: rates_on_device)."""
    if not (lr >= 0 and math.isfinite(lr)):
        raise ValueError(f"the position learning rate must be a finite number >= 0, got {lr}")
    for group in optimizers["means"].param_groups:
        if isinstance(group["lr"], torch.Tensor):
            group["lr"].fill_(lr)  # a launch with the number in it: nothing waits
        else:
            group["lr"] = lr


def rates_on_device(optimizers: Optimizers) -> None:
    """What a step replayed as a CUDA graph needs of the model's Adams (graphed_step.py): the position learning rate,
    which changes every step, as a tensor of one on the parameters' device (set_means_lr writes it there; the graph
    reads it), and on CUDA every group `capturable`, which torch asks of an Adam stepped in a capture. In the dtype
    torch's fused Adam reads it in: float32 on CUDA; on the CPU it reads a double, as from a number."""
    for key, optimizer in optimizers.items():
        for group in optimizer.param_groups:
            device = group["params"][0].device
            if key == "means" and not isinstance(group["lr"], torch.Tensor):
                dtype = torch.float32 if device.type == "cuda" else torch.float64
                group["lr"] = torch.full((), float(group["lr"]), dtype=dtype, device=device)
            if device.type == "cuda":
                group["capturable"] = True
        # its steps run both captured and not (refine steps, a new phase's first steps): torch need not warn of it
        optimizer._warned_capturable_if_run_uncaptured = True


def portable_state_dict(optimizer: torch.optim.Optimizer) -> dict:
    """optimizer.state_dict() with its learning rates as numbers and nothing capturable, as make_optimizers makes
    them: a checkpoint of a run replayed as a CUDA graph resumes anywhere (one read of each rate)."""
    state = optimizer.state_dict()
    for group in state["param_groups"]:  # copies of the optimizer's groups
        if isinstance(group["lr"], torch.Tensor):
            group["lr"] = float(group["lr"])
        group["capturable"] = False
    return state


# ------------------------------------------------------------------------------------------------- row surgery
def _optimizer_of(optimizers: Optimizers, param: torch.nn.Parameter) -> torch.optim.Optimizer | None:
    for optimizer in optimizers.values():
        for group in optimizer.param_groups:
            if any(p is param for p in group["params"]):
                return optimizer
    return None


def _row_state_items(state: dict, num_rows: int, param_shape: torch.Size):
    """The per-row tensors of one parameter's optimizer state (exp_avg, exp_avg_sq, ...), not the step counter."""
    for name, value in state.items():
        if isinstance(value, torch.Tensor) and value.dim() > 0 and value.shape == param_shape:
            yield name, value


def _replace(model: GaussianModel, optimizers: Optimizers, key: str, new_data: torch.Tensor, state_fn) -> None:
    """Swap model.params[key] for a Parameter holding `new_data`; map each per-row state tensor through state_fn."""
    old = model.params[key]
    new = torch.nn.Parameter(new_data, requires_grad=old.requires_grad)
    optimizer = _optimizer_of(optimizers, old)
    if optimizer is not None:
        for group in optimizer.param_groups:
            group["params"] = [new if p is old else p for p in group["params"]]
        state = optimizer.state.pop(old, None)
        if state is not None:
            for name, value in list(_row_state_items(state, old.shape[0], old.shape)):
                state[name] = state_fn(value)
            optimizer.state[new] = state
    model.params[key] = new


def append_rows(model: GaussianModel, optimizers: Optimizers, rows: Mapping[str, torch.Tensor]) -> None:
    """Append rows to every parameter; `rows` holds one tensor per key, all with the same number of rows.

    The new rows get zero Adam moments; the step counters are untouched (as 3DGS and gsplat do).
    """
    if set(rows) != set(PARAM_KEYS):
        raise ValueError(f"append_rows needs exactly the keys {list(PARAM_KEYS)}, got {sorted(rows)}")
    counts = {rows[key].shape[0] for key in PARAM_KEYS}
    if len(counts) != 1:
        raise ValueError(f"append_rows: all keys must have the same number of rows, got {counts}")
    if counts == {0}:
        return
    for key in PARAM_KEYS:
        old = model.params[key]
        extra = rows[key].detach().to(dtype=old.dtype, device=old.device)
        if extra.shape[1:] != old.shape[1:]:
            raise ValueError(f"append_rows: {key} rows must have shape [M, {', '.join(map(str, old.shape[1:]))}], "
                             f"got {list(extra.shape)}")
        _replace(model, optimizers, key, torch.cat([old.detach(), extra], dim=0),
                 lambda value, m=extra.shape[0]: torch.cat([value, value.new_zeros((m,) + value.shape[1:])], dim=0))


def remove_rows(model: GaussianModel, optimizers: Optimizers, mask: torch.Tensor) -> None:
    """Remove the rows where the boolean `mask` [N] is True, from every parameter and its Adam state."""
    n = model.num_gaussians
    if mask.dtype != torch.bool or tuple(mask.shape) != (n,):
        raise ValueError(f"remove_rows needs a boolean mask of shape [{n}], got {mask.dtype} {list(mask.shape)}")
    keep = ~mask.to(model.means.device)
    if bool(keep.all()):
        return
    for key in PARAM_KEYS:
        _replace(model, optimizers, key, model.params[key].detach()[keep].clone(), lambda value: value[keep].clone())


@torch.no_grad()
def copy_rows(model: GaussianModel, src: torch.Tensor, dst: torch.Tensor) -> None:
    """params[dst] = params[src] for every parameter, in place. Adam state is not touched."""
    src, dst = _indices(model, src), _indices(model, dst)
    if src.shape != dst.shape:
        raise ValueError(f"copy_rows: src and dst must have the same length, got {src.shape[0]} and {dst.shape[0]}")
    for key in PARAM_KEYS:
        param = model.params[key]
        param[dst] = param[src]


@torch.no_grad()
def set_rows(model: GaussianModel, indices: torch.Tensor, values: Mapping[str, torch.Tensor]) -> None:
    """params[key][indices] = values[key] in place, for the given keys only. Adam state is not touched."""
    indices = _indices(model, indices)
    for key, value in values.items():
        param = model.params[key]
        param[indices] = value.to(dtype=param.dtype, device=param.device)


@torch.no_grad()
def zero_moments(optimizers: Optimizers, indices: torch.Tensor, keys: tuple[str, ...] | None = None) -> None:
    """Zero the per-row Adam state (exp_avg, exp_avg_sq, ...) at `indices` for the optimizers of `keys` (default:
    all). The step counters are untouched. Optimizers that have not stepped yet have no state: nothing to do."""
    indices = torch.as_tensor(indices)
    if indices.dtype == torch.bool:
        raise ValueError("zero_moments takes integer indices, not a boolean mask")
    indices = indices.long().reshape(-1)
    for key in keys or tuple(optimizers):
        optimizer = optimizers[key]
        for group in optimizer.param_groups:
            for param in group["params"]:
                state = optimizer.state.get(param)
                if not state:
                    continue
                for _, value in _row_state_items(state, param.shape[0], param.shape):
                    value[indices.to(value.device)] = 0


def _indices(model: GaussianModel, indices: torch.Tensor) -> torch.Tensor:
    indices = torch.as_tensor(indices, device=model.means.device)
    if indices.dtype == torch.bool:
        raise ValueError("row helpers take integer indices, not a boolean mask")
    return indices.long().reshape(-1)
