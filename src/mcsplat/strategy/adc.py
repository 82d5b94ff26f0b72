"""The adaptive density control of 3DGS (Kerbl et al. 2023): the baseline the MCMC paper compares against.

- After every backward (`step_post_backward`, while step < densify_stop): for every visible Gaussian, accumulate the
  norm of its screen-space position gradient in NDC units (strategy/screen_gradients.py, shared with MCMC's
  automatic cap), and track its largest screen radius.
- Every densify_every steps with densify_start < step < densify_stop (0-based; steps 600..14900 by default), with
  g the mean accumulated gradient since the last densification:
  * clone the Gaussians with g >= grad_threshold whose largest scale is <= percent_dense R (an identical copy);
  * split those with g >= grad_threshold and a larger scale into two, positions drawn from the parent's Gaussian,
    scales divided by 1.6, the parent removed;
  * prune those with opacity < min_opacity and, after the first opacity reset (step > reset_every), those whose
    largest scale exceeds max_world_size R;
  * reset the accumulators.
  New rows start with zero Adam moments.
- Every reset_every steps (and step < densify_stop): opacities = min(opacity, reset_opacity), opacity moments zeroed;
  on a white background also at densify_start (3DGS's rule; `reset_at_start` sets it either way).
- Optional budget (cap_max): the paper's "3DGS with a budget" stops densifying at the budget. A densification that
  would exceed it keeps only the candidates with the largest gradients that fit (clone and split add one each).
  A model that starts above the budget is not cut (pruning by opacity and size goes on as usual).

Differences from the reference code (graphdeco-inria/gaussian-splatting):
- it densifies before the optimizer step of the same iteration (whose update is then lost with the rebuilt
  Parameters); here it happens after the step (as in gsplat), and its iterations are 1-based;
- its screen-size prune (max radius > 20 px) is dead code: densification resets max_radii2D to zero just before the
  test (graphdeco #123, #544, #643; the authors keep it for the paper's numbers). Here the radii are tracked and the
  prune is available (`screen_size_prune=True`), off by default so the baseline matches the published one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Mapping

import torch

from ..gaussians import PARAM_KEYS, GaussianModel
from ..geometry.rotation import quaternion_to_rotation
from ..optim import append_rows, remove_rows, set_rows, zero_moments
from .base import ALONE, AT_STEP, EVERY, RefineReport, Schedule, l1_regularizers
from .screen_gradients import ScreenGradients

__all__ = ["ADCConfig", "ADCSchedule", "ADCStrategy", "ADCReport"]

Optimizers = Mapping[str, torch.optim.Optimizer]

SPLIT_CHILDREN = 2            # 3DGS's N in densify_and_split
SPLIT_SCALE_DIVISOR = 0.8 * SPLIT_CHILDREN


# The densification schedule and the budget here are the options: the strategy follows its ADCSchedule, which a
# run's plan makes from them (fitted to the run's length, a planned cap).
@dataclass(frozen=True)
class ADCConfig:
    """3DGS defaults (its OptimizationParams), with 0-based steps."""

    grad_threshold: float = 0.0002   # densify_grad_threshold, in NDC units
    densify_start: int = 500         # densify when densify_start < step < densify_stop ...
    densify_stop: int = 15_000
    densify_every: int = 100         # ... and step % densify_every == 0
    reset_every: int = 3000          # opacity reset period
    reset_opacity: float = 0.01      # opacities are clamped to at most this at a reset
    min_opacity: float = 0.005       # prune below
    percent_dense: float = 0.01      # clone / split boundary: largest scale vs percent_dense x scene radius
    max_screen_size: float = 20      # pixels; used only with screen_size_prune (see the module docstring)
    screen_size_prune: bool = False
    max_world_size: float = 0.1      # prune when the largest scale exceeds max_world_size x scene radius
    cap_max: int | None = None       # optional budget: densification stops there
    reset_at_start: bool | None = None  # also reset at densify_start; None: on white backgrounds, as 3DGS does
    # The MCMC paper's L1 regularizers on ADC, for its Table 3's "3DGS + our regularizers"; 3DGS has none.
    opacity_reg: float = 0.0         # weight of mean(opacity)
    scale_reg: float = 0.0           # weight of mean(scale)

    def __post_init__(self) -> None:
        for name in ("grad_threshold", "percent_dense", "max_screen_size", "max_world_size", "opacity_reg",
                     "scale_reg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if self.densify_every < 1 or self.reset_every < 1:
            raise ValueError(f"densify_every and reset_every must be >= 1, got {self.densify_every}, "
                             f"{self.reset_every}")
        if self.densify_start < 0 or self.densify_stop < 0:
            raise ValueError(f"densify_start and densify_stop must be >= 0, got {self.densify_start}, "
                             f"{self.densify_stop}")
        for name in ("min_opacity", "reset_opacity"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        if self.cap_max is not None:
            if int(self.cap_max) != self.cap_max or self.cap_max < 1:
                raise ValueError(f"cap_max must be a whole number >= 1 or None, got {self.cap_max}")
            object.__setattr__(self, "cap_max", int(self.cap_max))  # frozen: normalised while it is being made


@dataclass(frozen=True)
class ADCSchedule(Schedule):
    """When ADC densifies and resets opacities, and its budget: what a run's plan decides (the options' values fitted
    to the run's length, a planned cap; mcsplat.planning)."""

    densify_start: int = field(default=500, metadata=AT_STEP)
    densify_stop: int = field(default=15_000, metadata=AT_STEP)
    densify_every: int = field(default=100, metadata=EVERY)
    reset_every: int = field(default=3000, metadata=EVERY)
    cap_max: int | None = None

    @classmethod
    def of(cls, config: ADCConfig) -> "ADCSchedule":
        """The options' values as they are (a strategy made without a plan)."""
        return cls(**{f.name: getattr(config, f.name) for f in fields(cls)})


@dataclass(frozen=True)
class ADCReport(RefineReport):
    """What ADC did after one optimizer step."""

    cloned: int = 0
    split: int = 0
    pruned: int = 0
    reset: bool = False  # opacities were reset (counted as 1)


class ADCStrategy:
    """3DGS adaptive density control behind the Strategy protocol (mcsplat.strategy.base)."""

    def __init__(self, config: ADCConfig | None = None, scene_radius: float = 1.0,
                 generator: torch.Generator | None = None, white_background: bool = False,
                 schedule: ADCSchedule | None = None) -> None:
        """`white_background`: the scene is trained over white, where 3DGS also resets opacities at densify_start
        (unless `config.reset_at_start` says otherwise); `schedule`: the run's plan's (default: the configuration's
        values as they are)."""
        if not (scene_radius > 0 and math.isfinite(scene_radius)):
            raise ValueError(f"scene_radius must be a positive number, got {scene_radius}")
        self.config = config or ADCConfig()
        self.schedule = schedule or ADCSchedule.of(self.config)
        self.reset_at_start = white_background if self.config.reset_at_start is None else self.config.reset_at_start
        self.scene_radius = scene_radius
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.gradients = ScreenGradients()          # NDC gradient norms and view counts since the last densification
        self.max_radii: torch.Tensor | None = None  # [N] largest screen radius (pixels) since then
        self.collective = ALONE  # several processes: each gathers statistics from its own views

    # --------------------------------------------------------------------------------------------- statistics
    def _reset_stats(self, n: int, device: torch.device) -> None:
        self.gradients.reset(n, device)
        self.max_radii = torch.zeros(n, dtype=torch.float32, device=device)

    def _ensure_stats(self, model: GaussianModel) -> None:
        n, device = model.num_gaussians, model.means.device
        if self.max_radii is None or self.max_radii.shape[0] != n:
            self._reset_stats(n, device)
        elif self.max_radii.device != device:
            self.gradients.to(device)
            self.max_radii = self.max_radii.to(device)

    def follow(self, schedule: ADCSchedule) -> None:
        """Densify on `schedule` from the next step on (--budget plans the run again as it goes)."""
        self.schedule = schedule

    def is_densify_step(self, step: int) -> bool:
        s = self.schedule
        return s.densify_start < step < s.densify_stop and step % s.densify_every == 0

    def is_reset_step(self, step: int) -> bool:
        s = self.schedule
        if step >= s.densify_stop:
            return False
        return (step > 0 and step % s.reset_every == 0) or (self.reset_at_start and step == s.densify_start)

    # ------------------------------------------------------------------------------------------- the protocol
    def regularization(self, model: GaussianModel) -> torch.Tensor:
        return l1_regularizers(model, self.config.opacity_reg, self.config.scale_reg)

    @torch.no_grad()
    def step_post_backward(self, step: int, model: GaussianModel, render_result: Any, width: int,
                           height: int) -> None:
        if step >= self.schedule.densify_stop or model.num_gaussians == 0:
            return
        self._ensure_stats(model)
        visible = self.gradients.add(render_result, model.num_gaussians, width, height)
        radii = render_result.radii
        grown = torch.maximum(self.max_radii, radii.to(self.max_radii.dtype))
        self.max_radii.copy_(torch.where(visible, grown, self.max_radii))  # dense: no count of the visible ones

    @torch.no_grad()
    def step_post_optimizer(self, step: int, model: GaussianModel, optimizers: Optimizers,
                            means_lr: float) -> ADCReport:
        counts: dict[str, int] = {}
        if self.is_densify_step(step):
            counts = self._densify_and_prune(step, model, optimizers)
        reset = self.is_reset_step(step)
        if reset:
            self._reset_opacity(model, optimizers)
        return ADCReport(num_gaussians=model.num_gaussians, reset=reset, **counts)

    def state_dict(self) -> dict:
        return {"strategy": "adc", "config": asdict(self.config), "gradients": self.gradients.state_dict(),
                "max_radii": None if self.max_radii is None else self.max_radii.clone()}

    def load_state_dict(self, state: dict) -> None:
        if state.get("strategy") != "adc":
            raise ValueError(f"this is not an ADC strategy state (strategy={state.get('strategy')!r})")
        gradients, max_radii = state.get("gradients") or {}, state.get("max_radii")
        tensors = [gradients.get("total"), gradients.get("views"), max_radii]
        if any(t is None for t in tensors):
            self.gradients.load_state_dict({})
            self.max_radii = None
            return
        if len({t.shape for t in tensors}) != 1:
            raise ValueError("ADC state: the accumulators have different lengths")
        self.gradients.load_state_dict(gradients)
        self.max_radii = max_radii.clone()

    # ----------------------------------------------------------------------------------------- densification
    def _densify_and_prune(self, step: int, model: GaussianModel, optimizers: Optimizers) -> dict:
        c, cap = self.config, self.schedule.cap_max
        self._ensure_stats(model)
        self.collective.sum_(self.gradients.total)  # the statistics of every process's views, as one batch gives
        self.collective.sum_(self.gradients.views)
        self.collective.max_(self.max_radii)
        n = model.num_gaussians
        device = model.means.device
        grads = self.gradients.means()
        max_scale = model.scales.detach().max(dim=1).values
        candidates = grads >= c.grad_threshold
        if cap is not None:
            budget = max(cap - n, 0)  # clone and split each add one Gaussian
            if int(candidates.sum()) > budget:
                ranked = torch.where(candidates, grads, torch.full_like(grads, -1.0))
                keep = torch.topk(ranked, budget).indices
                candidates = torch.zeros_like(candidates)
                candidates[keep] = True
        small = max_scale <= c.percent_dense * self.scene_radius
        clone_idx = torch.nonzero(candidates & small)[:, 0]
        split_idx = torch.nonzero(candidates & ~small)[:, 0]

        params = {key: model.params[key].detach() for key in PARAM_KEYS}
        clones = {key: params[key][clone_idx] for key in PARAM_KEYS}
        children = self._split_children(model, split_idx)
        new_rows = {key: torch.cat([clones[key], children[key]]) for key in PARAM_KEYS}
        append_rows(model, optimizers, new_rows)
        # A clone inherits its parent's screen radius; split children are new (and smaller): zero.
        new_radii = torch.cat([self.max_radii[clone_idx],
                               torch.zeros(split_idx.numel() * SPLIT_CHILDREN, device=device)])
        max_radii = torch.cat([self.max_radii, new_radii])

        prune = model.opacities.detach() < c.min_opacity
        prune[split_idx] = True
        if step > self.schedule.reset_every:
            prune |= model.scales.detach().max(dim=1).values > c.max_world_size * self.scene_radius
            if c.screen_size_prune:
                prune |= max_radii > c.max_screen_size
        num_pruned = int(prune.sum()) - split_idx.numel()
        remove_rows(model, optimizers, prune)
        self._reset_stats(model.num_gaussians, device)
        return {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()), "pruned": num_pruned}

    def _split_children(self, model: GaussianModel, parents: torch.Tensor) -> dict[str, torch.Tensor]:
        """Two children per parent: means drawn from N(mean, Sigma), scales / 1.6, other parameters copied."""
        params = {key: model.params[key].detach()[parents] for key in PARAM_KEYS}
        k = SPLIT_CHILDREN
        scales = torch.exp(params["log_scales"]).repeat(k, 1)
        eta = torch.randn(scales.shape, generator=self.generator, device=self.generator.device,
                          dtype=scales.dtype).to(scales.device)
        rotations = quaternion_to_rotation(params["quats"]).repeat(k, 1, 1)
        offsets = torch.bmm(rotations, (eta * scales)[:, :, None])[:, :, 0]
        children = {key: params[key].repeat((k,) + (1,) * (params[key].dim() - 1)) for key in PARAM_KEYS}
        children["means"] = children["means"] + offsets
        children["log_scales"] = torch.log(scales / SPLIT_SCALE_DIVISOR)
        return children

    def _reset_opacity(self, model: GaussianModel, optimizers: Optimizers) -> None:
        """opacity = min(opacity, reset_opacity), and the opacity's Adam moments zeroed (as 3DGS replaces them)."""
        n = model.num_gaussians
        if n == 0:
            return
        above = torch.nonzero(model.opacities.detach() > self.config.reset_opacity)[:, 0]
        value = torch.logit(torch.tensor(self.config.reset_opacity, dtype=torch.float64))
        set_rows(model, above, {"opacity_logits": value.expand(above.numel())})
        zero_moments(optimizers, torch.arange(n, device=model.means.device), keys=("opacity_logits",))
