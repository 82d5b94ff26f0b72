"""The MCMC densification of Kheradmand et al. (NeurIPS 2024): relocation, growth, SGLD position noise, regularizers.

Per step, after the Adam steps (`step_post_optimizer`), in gsplat's order (since gsplat PR #431):

1. if step is a refine step (0-based: refine_start < step < refine_stop and step % refine_every == 0, i.e. steps
   600, 700, ..., 24900 with the defaults):
   a. if there are more than cap_max Gaussians, remove the least opaque ones down to cap_max (not in the official
      code nor in gsplat; gsplat #516 / PR #939 - an SfM init larger than the cap, or a smaller cap on resume);
   b. relocate the dead Gaussians onto live ones (docs/method.md, "Relocation of dead Gaussians");
   c. grow by 5% up to cap_max ("Growth"); with auto_cap, by at most the number of Gaussians whose screen
      gradient asks for more (strategy/auto_cap.py), so that the count stops where the scene needs no more;
2. add the SGLD noise to the positions ("SGLD position noise"), on every step, with the learning rate the caller passes
   (the position learning rate; strategy/noise.py has the variants the paper ablates).

How the official code (ubc-vision/3dgs-mcmc) differs (docs/method.md, "One training step" and the table at its end):
- its iterations are 1-based: it relocates at iterations 600..24900 (500 < it < 25000, it % 100 == 0) *before*
  that iteration's optimizer step, i.e. after 599 Adam updates; here (and in gsplat) the 0-based step 600 relocates
  after its own Adam step, i.e. after 601 updates;
- since rebuilding its Parameters drops their gradients, the official Adam update of every refine iteration that
  relocated or added anything is skipped. Here the Adam step comes first and is never skipped;
- its noise uses the learning rate of the current iteration, set before the step; gsplat's uses the rate after the
  scheduler step. Here the caller chooses (`means_lr`);
- it clamps the number of copies at 50 (gsplat: 51, the default here), and crashes when no Gaussian is alive
  (gsplat #1027) or above 2^24 Gaussians (torch.multinomial, gsplat #338); neither happens here.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Callable, ClassVar, Hashable, Literal, Mapping

import torch

from ..gaussians import DEAD_OPACITY, PARAM_KEYS, GaussianModel
from ..optim import append_rows, copy_rows, remove_rows, set_rows, zero_moments
from .auto_cap import (DEFAULT_DEMAND_SHARE, DEFAULT_DEMAND_THRESHOLD, DEFAULT_GAUSSIANS_PER_PIXEL, growth_demand,
                       pixel_ceiling)
from .base import ALONE, AT_STEP, DECAY, EVERY, PLANNED, RefineReport, Schedule, l1_regularizers
from .noise import (NOISE_GATE_CENTER, NOISE_GATE_K, NOISE_SCHEDULES, NoiseSchedule, inject_parameter_noise,
                    inject_position_noise, noise_gate)
from .health import HEALTH_LEVELS, SeenWindow, refine_health
from .relocation import (DEFAULT_COPY_FLOOR, DEFAULT_MAX_COPIES, MAX_OPACITY, copy_capacity, copy_opacity,
                         relocation_params, sample_by_weight, sample_hosts)
from .screen_gradients import ScreenGradients

__all__ = ["MCMCConfig", "MCMCSchedule", "MCMCStrategy", "MCMCReport", "inject_noise", "noise_gate", "relocate_dead",
           "grow", "prune_to_cap", "NOISE_GATE_K", "NOISE_GATE_CENTER"]

Optimizers = Mapping[str, torch.optim.Optimizer]
Agree = Callable[[torch.Tensor], torch.Tensor]


def _as_drawn(indices: torch.Tensor) -> torch.Tensor:
    return indices


# The refinement schedule, the cap and the growth rate here are the options: the strategy follows its MCMCSchedule,
# which a run's plan makes from them (fitted to the run's length, a planned cap and growth rate).
@dataclass(frozen=True)
class MCMCConfig:
    """The paper's defaults (docs/method.md)."""

    cap_max: int = 1_000_000        # the largest number of Gaussians (per scene in the official configs)
    noise_lr: float = 5e5           # lambda_noise
    opacity_reg: float = 0.01       # lambda_o   (mean of the activated opacities)
    scale_reg: float = 0.01         # lambda_Sigma (mean of the activated scales)
    refine_start: int = 500         # relocate / grow when refine_start < step < refine_stop ...
    refine_stop: int = 25_000
    refine_every: int = 100         # ... and step % refine_every == 0
    grow_rate: float = 1.05         # growth factor per refine step (at least: see growth_share)
    growth_share: float = 0.4       # the cap is reached by this share of the run at the latest (schedule.py)
    min_opacity: float = DEAD_OPACITY  # dead: opacity <= min_opacity
    max_copies: int = DEFAULT_MAX_COPIES  # N clamp in Eq. 9
    # "alive": no host takes more copies than keep an Eq. 9 opacity of copy_floor each, the model does not grow
    # while relocation left dead Gaussians unplaced, and growth stops for good where the scene stops asking for more
    # (the automatic cap's demand rule), however far below the cap; "paper": the paper's relocation and growth, up to
    # max_copies copies a host whatever their opacity, to the cap (docs/method.md, "When the cap is far above what
    # the scene needs").
    relocation: Literal["alive", "paper"] = "alive"
    copy_floor: float = DEFAULT_COPY_FLOOR
    auto_cap: bool = False          # grow only where the screen gradient asks for more (cap_max is then a ceiling)
    demand_threshold: float = DEFAULT_DEMAND_THRESHOLD  # the automatic cap's gradient threshold (3DGS's, NDC units)
    demand_share: float = DEFAULT_DEMAND_SHARE  # the automatic cap stops growth once D < demand_share N
    gaussians_per_pixel: float = DEFAULT_GAUSSIANS_PER_PIXEL  # the automatic cap's ceiling per training pixel (0: off)
    # The noise ablations of the paper's rebuttal and Table 3 (strategy/noise.py); the defaults are the method.
    noise_covariance: bool = True   # shape the position noise by the covariance Sigma
    noise_gated: bool = True        # move only the nearly transparent Gaussians (the opacity gate)
    noise_all_params: bool = False  # also add decaying noise to scales, rotations and opacities (Table 3)
    param_noise_decay: float = 0.9995  # that noise's decay per step (of a 30,000-step run: fitted with the schedules)
    noise_schedule: NoiseSchedule = "lr"  # what the noise factor follows over the run

    def __post_init__(self) -> None:
        if int(self.cap_max) != self.cap_max or self.cap_max < 1:
            raise ValueError(f"cap_max must be a whole number >= 1, got {self.cap_max}")
        for name in ("noise_lr", "opacity_reg", "scale_reg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        if self.refine_every < 1:
            raise ValueError(f"refine_every must be >= 1, got {self.refine_every}")
        if self.refine_start < 0 or self.refine_stop < 0:
            raise ValueError(f"refine_start and refine_stop must be >= 0, got {self.refine_start}, {self.refine_stop}")
        if not (math.isfinite(self.grow_rate) and self.grow_rate >= 1.0):
            raise ValueError(f"grow_rate must be a finite number >= 1, got {self.grow_rate}")
        if not 0.0 < self.growth_share <= 1.0:
            raise ValueError(f"growth_share must be in (0, 1], got {self.growth_share}")
        if not 0.0 <= self.min_opacity < 1.0:
            raise ValueError(f"min_opacity must be in [0, 1), got {self.min_opacity}")
        if not (math.isfinite(self.demand_threshold) and self.demand_threshold > 0):
            raise ValueError(f"demand_threshold must be a finite number > 0, got {self.demand_threshold}")
        if not 0.0 <= self.demand_share < 1.0:
            raise ValueError(f"demand_share must be in [0, 1), got {self.demand_share}")
        if not (math.isfinite(self.gaussians_per_pixel) and self.gaussians_per_pixel >= 0):
            raise ValueError(f"gaussians_per_pixel must be a finite number >= 0, got {self.gaussians_per_pixel}")
        if self.noise_schedule not in NOISE_SCHEDULES:
            raise ValueError(f"noise_schedule must be one of {', '.join(NOISE_SCHEDULES)}, "
                             f"got {self.noise_schedule!r}")
        if not 0.0 < self.param_noise_decay <= 1.0:
            raise ValueError(f"param_noise_decay must be in (0, 1], got {self.param_noise_decay}")
        if self.relocation not in ("alive", "paper"):
            raise ValueError(f"relocation must be alive or paper, got {self.relocation!r}")
        if not self.min_opacity < self.copy_floor < 1.0:
            raise ValueError(f"copy_floor must be above min_opacity ({self.min_opacity}) and below 1, got "
                             f"{self.copy_floor}")
        if not 1 <= self.max_copies <= 1000:
            raise ValueError(f"max_copies must be in [1, 1000], got {self.max_copies}")
        object.__setattr__(self, "cap_max", int(self.cap_max))  # frozen: normalised while it is being made


@dataclass(frozen=True)
class MCMCSchedule(Schedule):
    """When MCMC refines, up to how many Gaussians and how fast it grows: what a run's plan decides (the options'
    values fitted to the run's length, a planned cap and growth rate; mcsplat.planning)."""

    refine_start: int = field(default=500, metadata=AT_STEP)
    refine_stop: int = field(default=25_000, metadata=AT_STEP)
    refine_every: int = field(default=100, metadata=EVERY)
    cap_max: int = 1_000_000
    grow_rate: float = field(default=1.05, metadata=PLANNED)
    param_noise_decay: float = field(default=0.9995, metadata=DECAY)

    @classmethod
    def of(cls, config: MCMCConfig) -> "MCMCSchedule":
        """The options' values as they are (a strategy made without a plan)."""
        return cls(**{f.name: getattr(config, f.name) for f in fields(cls)})


# --------------------------------------------------------------------------------------------------- the pieces
@torch.no_grad()
def inject_noise(model: GaussianModel, factor: float, generator: torch.Generator) -> None:
    """The paper's position noise: means += factor * gate(o) * Sigma @ eta, eta ~ N(0, I3) (Eqs. 7-8; the variants
    are in strategy/noise.py). `factor` is lambda_noise x the current position learning rate."""
    inject_position_noise(model, factor, generator)


def _apply_eq9(model: GaussianModel, sources: torch.Tensor, min_opacity: float,
               max_copies: int) -> tuple[torch.Tensor, torch.Tensor]:
    """New opacity logits and log-scales for the sampled `sources` (Eq. 9): N = times sampled + 1."""
    counts = torch.bincount(sources, minlength=model.num_gaussians)[sources] + 1
    opacities, scales = relocation_params(model.opacities.detach()[sources], model.scales.detach()[sources],
                                          counts, n_max=max_copies, min_opacity=min_opacity)
    logits = torch.logit(opacities.to(torch.float64)).to(opacities.dtype)
    return logits, torch.log(scales)


def eq9_opacities(opacities: torch.Tensor, sources: torch.Tensor, max_copies: int,
                  min_opacity: float) -> torch.Tensor:
    """The Eq. 9 opacity each copy of `sources` (one index per copy) gets, from the hosts' `opacities` before the
    move; at min_opacity where Eq. 9 gives less (the clamp)."""
    if sources.numel() == 0:
        return opacities.new_zeros(0, dtype=torch.float64)
    counts = (torch.bincount(sources, minlength=opacities.shape[0])[sources] + 1).clamp(max=max_copies)
    return copy_opacity(opacities[sources].clamp(0.0, MAX_OPACITY), counts).clamp_min(min_opacity)


def _no_rows(model: GaussianModel) -> torch.Tensor:
    return torch.zeros(0, dtype=torch.long, device=model.means.device)


def _no_alive_warning(min_opacity: float, what: str) -> None:
    warnings.warn(f"MCMC: every Gaussian has opacity <= {min_opacity}, so there is nothing to copy from; {what} "
                  f"skipped (gsplat #1027)", RuntimeWarning, stacklevel=3)


def _draw_sources(weights: torch.Tensor, num: int, generator: torch.Generator, copy_floor: float | None,
                  max_copies: int) -> torch.Tensor:
    """`num` hosts drawn by weight (opacity), the paper's way (copy_floor None); or as many as the hosts can take
    while every copy keeps an Eq. 9 opacity of at least copy_floor (strategy/relocation.py, copy_capacity)."""
    if copy_floor is None:
        return sample_by_weight(weights, num, generator)
    return sample_hosts(weights, copy_capacity(weights, copy_floor, max_copies), num, generator)


@torch.no_grad()
def relocate_dead(model: GaussianModel, optimizers: Optimizers, generator: torch.Generator, *,
                  min_opacity: float = DEAD_OPACITY, max_copies: int = DEFAULT_MAX_COPIES,
                  copy_floor: float | None = None, agree: Agree = _as_drawn) -> tuple[torch.Tensor, torch.Tensor]:
    """Move the dead Gaussians (opacity <= min_opacity) onto live ones (docs/method.md, "Relocation of dead Gaussians").

    Sources are drawn from the live Gaussians with replacement, with probability proportional to opacity. Every dead
    slot takes its source's position, rotation and colour; the source and its copies all get the Eq. 9 opacity and
    scale. Adam moments are zeroed at the sources only; dead slots keep theirs (paper section 3.4, official #21).
    With `copy_floor` no host takes more copies than keep that opacity each (relocation "alive"): the dead that find
    no such host stay where they are. Returns (the relocated slots, their source indices). With nothing alive it
    warns and changes nothing. `agree` sees the drawn sources before they are used (several processes: rank 0's
    draw on all of them).
    """
    device = model.means.device
    empty = torch.zeros(0, dtype=torch.long, device=device)
    opacities = model.opacities.detach()
    dead = opacities <= min_opacity
    num_dead = int(dead.sum())
    if num_dead == 0:
        return empty, empty
    alive = torch.nonzero(~dead)[:, 0]
    if alive.numel() == 0:
        _no_alive_warning(min_opacity, "relocation")
        return empty, empty
    # All sampling happens before Eq. 9 changes anything.
    sources = agree(alive[_draw_sources(opacities[alive], num_dead, generator, copy_floor, max_copies)])
    slots = torch.nonzero(dead)[:, 0][:sources.shape[0]]
    logits, log_scales = _apply_eq9(model, sources, min_opacity, max_copies)
    copy_rows(model, sources, slots)
    both = torch.cat([sources, slots])
    set_rows(model, both, {"opacity_logits": torch.cat([logits, logits]),
                           "log_scales": torch.cat([log_scales, log_scales])})
    zero_moments(optimizers, sources)
    return slots, sources


@torch.no_grad()
def grow(model: GaussianModel, optimizers: Optimizers, generator: torch.Generator, *, cap_max: int,
         grow_rate: float = 1.05, min_opacity: float = DEAD_OPACITY, max_copies: int = DEFAULT_MAX_COPIES,
         copy_floor: float | None = None, agree: Agree = _as_drawn) -> torch.Tensor:
    """Append min(cap_max, int(grow_rate N)) - N copies of Gaussians drawn by opacity (docs/method.md, "Growth").

    The sources and the appended copies (the last rows, in the order of the returned source indices) get the Eq. 9
    opacity and scale; the copies have zero Adam moments and the sources' moments are zeroed. Note that
    int(1.05 N) == N below N = 20: a model that small does not grow (as in the official code). Nothing is added when
    no Gaussian is alive (with a warning) or when N >= cap_max. With `copy_floor`, fewer when the hosts cannot give
    that many copies that keep that opacity (relocate_dead). `agree` as in relocate_dead().
    """
    n = model.num_gaussians
    empty = torch.zeros(0, dtype=torch.long, device=model.means.device)
    num_add = min(cap_max, int(grow_rate * n)) - n
    if num_add <= 0:
        return empty
    opacities = model.opacities.detach()
    if not bool((opacities > min_opacity).any()):
        _no_alive_warning(min_opacity, "growth")
        return empty
    sources = agree(_draw_sources(opacities, num_add, generator, copy_floor, max_copies))
    if sources.numel() == 0:
        return empty
    logits, log_scales = _apply_eq9(model, sources, min_opacity, max_copies)
    set_rows(model, sources, {"opacity_logits": logits, "log_scales": log_scales})
    zero_moments(optimizers, sources)
    append_rows(model, optimizers, {key: model.params[key].detach()[sources] for key in PARAM_KEYS})
    return sources


@torch.no_grad()
def prune_to_cap(model: GaussianModel, optimizers: Optimizers, cap_max: int) -> int:
    """Keep the cap_max most opaque Gaussians when there are more (gsplat #516); returns the number removed."""
    n = model.num_gaussians
    if n <= cap_max:
        return 0
    keep = torch.topk(model.opacities.detach(), cap_max, sorted=False).indices
    remove = torch.ones(n, dtype=torch.bool, device=model.means.device)
    remove[keep] = False
    remove_rows(model, optimizers, remove)
    return n - cap_max


# ------------------------------------------------------------------------------------------------- the strategy
@dataclass(frozen=True)
class MCMCReport(RefineReport):
    """What MCMC did after one optimizer step."""

    relocated: int = 0
    added: int = 0
    pruned: int = 0
    demand: int | None = None  # --cap-max auto: D at this refine step (None: not measured at this step)
    # The instruments of strategy/health.py at this refine step (None: not a refine step).
    dead_share: float | None = None
    unseen_dead_share: float | None = None
    copies_max: float | None = None
    copies_mean: float | None = None
    born_dead_share: float | None = None
    unplaced: float | None = None
    LEVELS: ClassVar[tuple[str, ...]] = ("demand",) + HEALTH_LEVELS


# At the cap, a relocation that finds more than this share dead: with the paper's relocation each live Gaussian is
# split among several copies born at the dead opacity, and the share feeds itself until nearly all are dead
# (docs/method.md, "When the cap is far above what the scene needs"). Healthy runs stay below a quarter.
COLLAPSE_SHARE = 0.5


def collapse_warning(step: int, dead: int, count: int, cap: int) -> str | None:
    """The warning for a relocation at the cap that found more than COLLAPSE_SHARE of the Gaussians dead, or None.
    (Below the cap a large share is normal early on: random points in empty space die at the first relocations.)"""
    if count < cap or dead <= COLLAPSE_SHARE * count:
        return None
    return (f"MCMC step {step}: {dead / count:.0%} of the {count:,} Gaussians were dead at this relocation; past "
            f"half, the paper's relocation cannot keep up and the scene fades. The cap is likely far above what "
            f"this scene needs: leave --cap-max out (the count the scene asks for), or lower it")


class MCMCStrategy:
    """The paper's method behind the Strategy protocol (mcsplat.strategy.base)."""

    def __init__(self, config: MCMCConfig | None = None, scene_radius: float = 1.0,
                 generator: torch.Generator | None = None, image_pixels: int | None = None,
                 schedule: MCMCSchedule | None = None) -> None:
        """image_pixels: the pixels of a training image, for the automatic cap's ceiling (None: cap_max alone);
        schedule: the run's plan's (default: the configuration's values as they are)."""
        if not (scene_radius > 0 and math.isfinite(scene_radius)):
            raise ValueError(f"scene_radius must be a positive number, got {scene_radius}")
        self.config = config or MCMCConfig()
        self.schedule = schedule or MCMCSchedule.of(self.config)
        self.scene_radius = scene_radius  # the noise scale comes in through the position learning rate
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.collective = ALONE
        self.gradients = ScreenGradients()  # kept only with auto_cap
        self.seen = SeenWindow()  # which Gaussians a view composited since the last refine step (health.py)
        self.chosen_cap: int | None = None   # auto_cap: the count at which growth stopped
        self.image_pixels = image_pixels
        self.collapse_warned = False

    def follow(self, schedule: MCMCSchedule) -> None:
        """Refine on `schedule` from the next step on (--budget plans the run again as it goes)."""
        self.schedule = schedule

    @property
    def ceiling(self) -> int:
        """The most Gaussians growth may reach: cap_max, and under auto_cap the per-pixel ceiling where lower."""
        c, cap = self.config, self.schedule.cap_max
        return pixel_ceiling(cap, self.image_pixels, c.gaussians_per_pixel) if c.auto_cap else cap

    def is_refine_step(self, step: int) -> bool:
        s = self.schedule
        return s.refine_start < step < s.refine_stop and step % s.refine_every == 0

    def graph_phase(self, step: int) -> Hashable | None:
        """What the per-step work branches on at `step`, and where its statistics live, for a step replayed as a
        CUDA graph (graphed_step.py). None where a step cannot be replayed: a refine step (row surgery, counts read),
        the noise on every parameter (its strength follows the step) and no noise at all."""
        if self.is_refine_step(step) or self.config.noise_all_params or self.config.noise_lr == 0:
            return None  # (no noise: the plain step draws none, a graph would)
        collecting = self.asks_the_scene and self.chosen_cap is None
        return (step < self.schedule.refine_stop, collecting,
                *(t.data_ptr() if t is not None else None for t in (self.seen.seen, self.gradients.total,
                                                                     self.gradients.views)))

    def regularization(self, model: GaussianModel) -> torch.Tensor:
        """opacity_reg mean(sigmoid(o)) + scale_reg mean(exp(s)): means of the activated values, as the official
        code (the paper's Eq. 10 writes sums)."""
        return l1_regularizers(model, self.config.opacity_reg, self.config.scale_reg)

    def step_post_backward(self, step: int, model: GaussianModel, render_result: Any, width: int,
                           height: int) -> None:
        """Which Gaussians the view composited (the health instruments), and with auto_cap the screen-gradient
        statistic that decides the growth; the paper's MCMC keeps neither."""
        if step >= self.schedule.refine_stop or not model.num_gaussians:
            return
        self.seen.add(render_result, model.num_gaussians)
        if self.asks_the_scene and self.chosen_cap is None:
            self.gradients.add(render_result, model.num_gaussians, width, height)

    def step_post_optimizer(self, step: int, model: GaussianModel, optimizers: Optimizers,
                            means_lr: float | torch.Tensor) -> MCMCReport:
        c = self.config
        counts: dict[str, Any] = {}
        if self.is_refine_step(step):
            counts = self._refine(step, model, optimizers)
            if self.asks_the_scene and self.chosen_cap is None:
                self.gradients.reset(model.num_gaussians, model.means.device)
            self.seen.reset()
        inject_position_noise(model, c.noise_lr * means_lr, self.generator, covariance=c.noise_covariance,
                              gated=c.noise_gated)
        if c.noise_all_params:
            inject_parameter_noise(model, self.schedule.param_noise_decay ** step, self.generator,
                                   gated=c.noise_gated)
        return MCMCReport(num_gaussians=model.num_gaussians, **counts)

    def _refine(self, step: int, model: GaussianModel, optimizers: Optimizers) -> dict[str, Any]:
        """One refine step: down to the cap, relocation, growth; their counts and the health levels."""
        c, s = self.config, self.schedule
        counts: dict[str, Any] = {"pruned": prune_to_cap(model, optimizers, s.cap_max)}
        opacities = model.opacities.detach().clone()
        if model.num_gaussians and not bool((opacities > c.min_opacity).any()):
            warnings.warn(f"MCMC step {step}: every Gaussian has opacity <= {c.min_opacity}, so there is "
                          f"nothing to copy from; relocation and growth skipped (gsplat #1027)", RuntimeWarning,
                          stacklevel=3)
            return counts
        floor = c.copy_floor if c.relocation == "alive" else None
        cap, counts["demand"] = (self._auto_cap(model) if c.auto_cap else self._asked_cap(model)
                                 if c.relocation == "alive" else (s.cap_max, None))
        dead = opacities <= c.min_opacity
        unseen = self.seen.unseen_share(dead)
        slots, moved = relocate_dead(model, optimizers, self.generator, min_opacity=c.min_opacity,
                                     max_copies=c.max_copies, copy_floor=floor, agree=self.collective.agree)
        unplaced = int(dead.sum()) - int(slots.numel())
        warning = collapse_warning(step, int(dead.sum()), model.num_gaussians, cap)
        if warning is not None and not self.collapse_warned:
            warnings.warn(warning, RuntimeWarning, stacklevel=3)
            self.collapse_warned = True
        hosts_before_growth = model.opacities.detach().clone()
        # Relocation "alive": dead left unplaced mean no host can give a copy that stays alive; growth would only
        # add more of them.
        added = _no_rows(model) if unplaced and floor is not None else grow(
            model, optimizers, self.generator, cap_max=cap, grow_rate=s.grow_rate, min_opacity=c.min_opacity,
            max_copies=c.max_copies, copy_floor=floor, agree=self.collective.agree)
        counts["relocated"], counts["added"] = int(slots.numel()), int(added.numel())
        born = torch.cat([eq9_opacities(opacities, moved, c.max_copies, c.min_opacity),
                          eq9_opacities(hosts_before_growth, added, c.max_copies, c.min_opacity)])
        counts.update(refine_health(int(dead.numel()), int(dead.sum()), unseen, torch.cat([moved, added]), born,
                                    c.min_opacity, unplaced))
        return counts

    def _auto_cap(self, model: GaussianModel) -> tuple[int, int | None]:
        """(this refine step's cap, the demand D measured, or None) under auto_cap: the cap is N + D while
        D >= demand_share N; from the first step where it is not, the count of that step for the rest of the run;
        never above the ceiling."""
        n = model.num_gaussians
        if self.chosen_cap is not None:
            return min(self.ceiling, self.chosen_cap), None
        demand = self._growth_demand(model)
        if demand >= self.config.demand_share * n:
            return min(self.ceiling, n + demand), demand
        self.chosen_cap = n
        return min(self.ceiling, self.chosen_cap), demand

    @property
    def asks_the_scene(self) -> bool:
        """Whether growth asks the scene (the demand D) and stops where it asks for no more: the automatic cap, and
        relocation "alive" with a cap; `chosen_cap` is then where it stopped."""
        return self.config.auto_cap or self.config.relocation == "alive"

    def _asked_cap(self, model: GaussianModel) -> tuple[int, int | None]:
        """(this refine step's cap, the demand D measured, or None) with a number for the cap and relocation
        "alive": the paper's growth to cap_max while the scene asks for more; from the first refine step where
        D < demand_share N, the count of that step for the rest of the run, however far below cap_max (where the
        cap fits the scene, the demand lasts until it is reached: the paper's run). No view since the last refine
        step (a strategy driven without renders): no decision."""
        n, cap = model.num_gaussians, self.schedule.cap_max
        if self.chosen_cap is not None:
            return min(cap, self.chosen_cap), None
        demand = self._growth_demand(model)
        if self.gradients.views is None or not bool(self.gradients.views.any()):
            return cap, None
        if demand < self.config.demand_share * n:
            self.chosen_cap = n
            return min(cap, n), demand
        return cap, demand

    def _growth_demand(self, model: GaussianModel) -> int:
        """The automatic cap's D, from every process's views when several train together."""
        g = self.gradients
        if g.total is not None:
            self.collective.sum_(g.total)
            self.collective.sum_(g.views)
        return growth_demand(g, model.opacities.detach(), self.config.demand_threshold, self.config.min_opacity)

    def state_dict(self) -> dict:
        """The automatic cap's statistic (the generator belongs to the caller: save it there)."""
        return {"strategy": "mcmc", "config": asdict(self.config), "gradients": self.gradients.state_dict(),
                "chosen_cap": self.chosen_cap}

    def load_state_dict(self, state: dict) -> None:
        if state.get("strategy") != "mcmc":
            raise ValueError(f"this is not an MCMC strategy state (strategy={state.get('strategy')!r})")
        self.gradients.load_state_dict(state.get("gradients") or {})
        self.chosen_cap = state.get("chosen_cap")
