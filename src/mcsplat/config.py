"""What the user asked of a training run: frozen dataclasses that tyro turns into the `mcsplat train` options.

The configuration is one value that nothing changes once it is made (`dataclasses.replace` derives another). What a
run decides as it goes (its steps, the schedules fitted to them, the cap and growth rate, the number of processes) is
its plan (mcsplat.planning), made from this and handed to the step and the strategy beside it.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Sequence

import tyro

from .appearance.options import AppearanceOptions
from .typed_json import checked_dataclass, flat_groups
from .data.attachments.depth import DepthOptions
from .data.attachments.masks import MaskOptions
from .depth_supervision.correlation import DepthCorrelationOptions
from .depth_supervision.terms import DepthTermOptions
from . import option_checks
from .errors import MCSplatError
from .features import features_named
from .optim import OptimConfig
from .pose_refinement import PoseOptions
from .strategy.adc import ADCConfig
from .strategy.mcmc import MCMCConfig
from .surface_terms import SurfaceOptions

# How an option is treated on --resume, as metadata of its field (`resume_policy`): "process" options only affect
# how this process runs, and come from the command line; "place" options say where the scene and the run folder are
# now, which may change; every other option comes from the run's saved configuration (steps included: the
# learning-rate schedule depends on it), and a command line that gives it another value is refused.
PROCESS = {"resume": "process"}
PLACE = {"resume": "place"}


@dataclass(frozen=True)
class ModelConfig:
    """Initial Gaussians."""

    init: Literal["auto", "sfm", "triangulate", "frustum", "random"] = "auto"
    """auto: the scene's SfM points; else random in a cube for a synthetic scene (images with alpha), and points
    triangulated from the known poses for a real capture (random in the cameras' frustums where that fails).
    random: the paper's "Ours (Random)" (the official code's default)."""
    num_init_points: int = 100_000
    """Points of a random (cube or frustum) initialisation."""
    init_extent: float = 3.0
    """Random init fills [-extent R, extent R]^3 around the world origin (Blender scenes: [-1.3, 1.3]^3)."""
    init_scale: float | None = None
    """Initial scale = init_scale x RMS distance to the 3 nearest neighbours. Default: the strategy's own, 0.1 for
    MCMC (the paper's code) and 1.0 for ADC (3DGS's)."""
    init_opacity: float | None = None
    """Default: the strategy's own, 0.5 for MCMC and 0.1 for ADC."""
    sh_degree: int = 3


@dataclass(frozen=True)
class ViewerOptions:
    """The live viewer of the training (this process's own: --resume takes them from its command line)."""

    viewer: bool = field(default=False, metadata=PROCESS)
    """Serve a live web viewer of the training (needs `pip install mcsplat[viewer]`)."""
    port: int = field(default=8080, metadata=PROCESS)
    """Port of the live viewer."""
    host: str = field(default="127.0.0.1", metadata=PROCESS)
    """Address the live viewer listens on; 0.0.0.0 exposes it to the network."""
    viewer_origin: tuple[str, ...] = field(default=(), metadata=PROCESS)
    """Web pages (host names or origins such as http://myhost:8080) allowed to connect to the viewer besides its own
    page: where it is reached under a name, or through a proxy."""


@dataclass(frozen=True)
class TrainConfig:
    """Train a 3D Gaussian Splatting scene with the MCMC method (or the 3DGS ADC baseline)."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATA")] = field(metadata=PLACE)
    """Scene folder: COLMAP, NeRF/Blender transforms or LLFF poses_bounds (auto-detected)."""
    out: Path | None = field(default=None, metadata=PLACE)
    """Run directory (default: runs/<scene folder name>)."""
    strategy: Literal["mcmc", "adc"] = "mcmc"
    """mcmc: the paper's method. adc: classic 3DGS densification, the baseline."""
    cap_max: int | Literal["auto"] | None = None
    """Maximum number of Gaussians (sets --mcmc.cap-max, or --adc.cap-max for the budgeted baseline); MCMC grows to
    it at the paper's rate, stopping earlier only where the views ask for no more. Default (or auto), MCMC: grow only
    while the screen gradients ask for more Gaussians, up to --mcmc.cap-max (the paper's 1,000,000) and 3 per
    training pixel (see the README)."""
    steps: int = 30_000
    """Training steps (the paper: 30,000). The step schedules follow it (--scale-schedule)."""
    budget: str | None = None
    """Train for this much time on this machine instead of a number of steps: '10m', '90s', '1.5h' or minutes
    ('10'). The steps, the cap and the coarse-to-fine resolution are planned from the step time measured as the run
    goes (set-up, the final evaluation and the export are not counted); see the README."""
    scale_schedule: bool = True
    """Fit every step schedule (refinement, ADC's densification and opacity resets, the SH increase) to the run's
    length: the options give the paper's values for 30,000 steps and a run of N steps multiplies them by N / 30,000
    (gsplat's steps_scaler). --no-scale-schedule takes them as steps of this run."""
    resolution_start: float | None = None
    """Coarse to fine: the share of the full image size the first step trains at, rising to full size at
    --resolution-full-at of the run (default: 0.25 with --budget, else 1, full size throughout)."""
    resolution_full_at: float | None = None
    """The share of the run by which training reaches the full image size (default: with --budget, chosen from the
    share of a step its pixels take, 0.4 to 1; else 0.4)."""
    downscale: int = 1
    """Image downscale factor (uses images_N/ when the scene has it)."""
    test_every: int = 8
    """Every N-th image is held out for testing (Blender scenes use their own test split)."""
    background: Literal["auto", "white", "black"] = "auto"
    """auto: white when the images have an alpha channel (a synthetic object, as the paper), black otherwise."""
    training_masks: Annotated[MaskOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=MaskOptions)
    depth_maps: Annotated[DepthOptions, tyro.conf.OmitArgPrefixes] = field(
        default_factory=lambda: DepthOptions(depths="none"))
    device: Literal["auto", "cpu", "cuda"] = field(default="auto", metadata=PROCESS)
    """auto: CUDA when available, else CPU."""
    seed: int = 0
    """Random seed of the initialisation, the view order, relocation and noise."""
    threads: int | None = field(default=None, metadata=PROCESS)
    """CPU threads (default: all cores)."""
    cuda_graph: bool = field(default=False, metadata=PROCESS)
    """On a GPU, replay the training step as a CUDA graph: its launches recorded once and replayed with one call, far
    less work for the host each step. Recorded again when the image size, the SH degree or the number of Gaussians
    changes; refine steps run as before, and so do runs with per-image modules, the depth or --surface terms, ADC or
    several processes. Experimental (its speed is not measured yet); the CPU runs its steps as they are."""
    eval_every: int = field(default=0, metadata=PROCESS)
    """Evaluate on the test views every N steps (0: only at the end)."""
    save_every: int = field(default=5000, metadata=PROCESS)
    """Write a checkpoint every N steps (and on Ctrl-C or SIGTERM)."""
    save_every_minutes: float = field(default=10.0, metadata=PROCESS)
    """Also write one when this many minutes have passed since the last (0: off)."""
    resume: bool = field(default=False, metadata=PLACE)
    """Continue from the run directory's checkpoint."""
    overwrite: bool = field(default=False, metadata=PLACE)
    """Allow writing into a run directory that already holds a run (files are replaced, never deleted)."""
    quiet: bool = field(default=False, metadata=PROCESS)
    """No progress bar or messages (for scripts); the final scores and the files written are still printed."""
    sh_increase_every: int = 1000
    """The active SH degree grows by one every N steps up to the model's degree."""
    ssim_weight: float = 0.2
    """Weight of D-SSIM in the loss; L1 gets the rest (the paper: 0.2)."""
    compensation: Annotated[AppearanceOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=AppearanceOptions)
    poses: Annotated[PoseOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=PoseOptions)
    surface_terms: Annotated[SurfaceOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=SurfaceOptions)
    depth_terms: Annotated[DepthTermOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=DepthTermOptions)
    depth_prior: Annotated[DepthCorrelationOptions, tyro.conf.OmitArgPrefixes] = field(
        default_factory=DepthCorrelationOptions)
    antialiased: bool = False
    """Mip-Splatting's 2D filter: a splat's opacity shrinks as the 0.3 px screen-space blur widens it, so fine
    detail keeps its weight when the scene is seen from farther away or at a lower resolution than it was trained
    at. The trained scene is always drawn this way (eval, viewer, renders; .spz records it)."""
    lpips_net: Literal["alex", "vgg"] = "vgg"
    """LPIPS backbone for the final metrics (the paper reports VGG)."""
    save_renders: bool = True
    """Write the final test renders as PNG."""
    live_viewer: Annotated[ViewerOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=ViewerOptions)
    dist_timeout: float = field(default=600.0, metadata=PROCESS)
    """Under torchrun: seconds a process waits for the others before it stops with an error (a process died or
    hangs)."""
    block: Annotated[str | None, tyro.conf.Suppress] = None
    """The block of a partitioned scene this run trains, as PLAN_FILE#INDEX with the plan's path from the run folder
    (`mcsplat blocks train` sets it): the block's views and the points of its region only (partition/)."""
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    mcmc: MCMCConfig = field(default_factory=MCMCConfig)
    adc: ADCConfig = field(default_factory=ADCConfig)
    named: Annotated[frozenset[str] | None, tyro.conf.Suppress] = field(
        default=None, compare=False, repr=False, metadata={"saved": False})
    """The options the command line named, as config.json's keys (named_options; not an option itself, nor saved)."""

    def __post_init__(self) -> None:
        # Each strategy starts from the initial Gaussians its own code uses (as in gsplat).
        scale, opacity = INITIAL_GAUSSIANS.get(self.strategy, INITIAL_GAUSSIANS["mcmc"])
        self._derive(model=dataclasses.replace(self.model, init_scale=_default(self.model.init_scale, scale),
                                               init_opacity=_default(self.model.init_opacity, opacity)))
        not_finite = non_finite_options(self)  # first: inf passes every range check below without an upper end
        if not_finite:
            raise MCSplatError(f"{', '.join(not_finite)}: not a finite number; give one within the option's range "
                               f"(--help says it)")
        checks = [(self.steps >= 1, "--steps must be at least 1"),
                  (self.downscale >= 1, "--downscale must be at least 1"),
                  (self.eval_every >= 0, "--eval-every must be 0 (off) or positive"),
                  (self.save_every >= 0, "--save-every must be 0 (off) or positive"),
                  (self.save_every_minutes >= 0, "--save-every-minutes must be 0 (off) or positive"),
                  (self.cap_max in (None, "auto") or self.cap_max >= 1, "--cap-max must be at least 1 or auto"),
                  (self.cap_max != "auto" or self.strategy == "mcmc",
                   "--cap-max auto is for the MCMC strategy (ADC's growth has its own rule); give ADC a number"),
                  (self.threads is None or self.threads >= 1, "--threads must be at least 1"),
                  (self.sh_increase_every >= 1, "--sh-increase-every must be at least 1"),
                  (self.dist_timeout > 0, "--dist-timeout must be positive"),
                  (self.depth_terms.depth_loss == "none" or self.depth_maps.depths != "none",
                   f"--depth-loss {self.depth_terms.depth_loss} reads depth maps, and --depths is 'none': give "
                   "--depths auto (beside the photos, or the scene's depths/) or the folder that holds them"),
                  (0.0 <= self.ssim_weight <= 1.0, "--ssim-weight must be in [0, 1]"),
                  (self.resolution_start is None or 0.0 < self.resolution_start <= 1.0,
                   "--resolution-start must be in (0, 1] (1: full size from the first step)"),
                  (self.resolution_full_at is None or 0.0 < self.resolution_full_at <= 1.0,
                   "--resolution-full-at must be in (0, 1]"),
                  (0 <= self.model.sh_degree <= 3, "--model.sh-degree must be 0..3"),
                  (self.model.num_init_points >= 1, "--model.num-init-points must be at least 1"),
                  (self.model.init_extent > 0, "--model.init-extent must be positive"),
                  (0.0 < self.model.init_opacity < 1.0, "--model.init-opacity must be in (0, 1)"),
                  (self.model.init_scale > 0, "--model.init-scale must be positive"),
                  (not (self.resume and self.overwrite), "--resume and --overwrite exclude each other")]
        for ok, message in checks:
            if not ok:
                raise MCSplatError(message)
        refuse_unused_options(self)
        if self.budget is not None:
            budget_seconds(self.budget)  # a one-line error for a budget it cannot read
        # Coarse to fine under --budget; --cap-max goes to the strategy that takes it.
        mcmc, adc = self.mcmc, self.adc
        if self.cap_max == "auto" or (self.cap_max is None and self.strategy == "mcmc"):
            # No number: MCMC grows to what the scene asks for, up to --mcmc.cap-max (the paper's 1M) at most.
            mcmc = dataclasses.replace(mcmc, auto_cap=True)
        elif self.cap_max is not None:  # a number: the run grows to it at the paper's rate
            mcmc = dataclasses.replace(mcmc, cap_max=self.cap_max, auto_cap=False)
            adc = dataclasses.replace(adc, cap_max=self.cap_max)
        resolution = _default(self.resolution_start, BUDGET_RESOLUTION_START if self.budget is not None else 1.0)
        self._derive(resolution_start=resolution, mcmc=mcmc, adc=adc)

    def _derive(self, **values: Any) -> None:
        """Set the values that follow from other options, only while the configuration is being made (__post_init__):
        it is frozen from then on."""
        for name, value in values.items():
            object.__setattr__(self, name, value)

    @property
    def max_gaussians(self) -> int | None:
        """The most Gaussians the run may hold, whatever its plan: MCMC's cap (the ceiling of the count the scene
        asks for, unless --cap-max gives a number), ADC's optional budget (None: no limit). The one rule for it:
        the initialisation, --budget and blocks read it here; the plan's cap, config.json's `mcmc.cap_max` on a
        --budget run, is at most this."""
        return self.mcmc.cap_max if self.strategy == "mcmc" else self.adc.cap_max

    @property
    def run_dir(self) -> Path:
        return self.out if self.out is not None else Path("runs") / Path(self.data).resolve().name


def _default(value: Any, default: Any) -> Any:
    return default if value is None else value


def feature_groups(config: TrainConfig) -> list[Any]:
    """The option groups of `config` whose flags have no prefix (features.py: each says what its feature adds to a
    run), in the order TrainConfig declares them."""
    return [getattr(config, name) for name in flat_groups(TrainConfig)]


def unused_options(config: TrainConfig) -> list[tuple[list[str], str]]:
    """The options the command line gave (`config.named`) to a new run that its groups say would be ignored (the
    --surface-* options without --surface), as it gave them, each group's with the reason (a resumed run's options are
    its own: run_start compares the options given with them)."""
    if config.resume or not config.named:
        return []
    found = []
    for group in features_named(feature_groups(config), "unused_options"):
        given = [f"--{name.replace('_', '-')} {getattr(group, name)}" for name in group.unused_options()
                 if name in config.named]
        if given:
            found.append((given, group.unused_reason))
    return found


def refuse_unused_options(config: TrainConfig) -> None:
    for given, reason in unused_options(config):
        raise MCSplatError(f"{', '.join(given)}: {reason}")


def non_finite_options(config: TrainConfig) -> list[str]:
    """The float options of `config` and of its model group that hold inf or nan, as the command line gives them (the
    other groups check their own as they are made)."""
    return option_checks.non_finite_options(config) + option_checks.non_finite_options(config.model, "model.")


def resume_policy(key: str) -> str | None:
    """How --resume treats the option of config.json's `key`: "process" (this process's own: from the command
    line), "place" (where the scene and the run folder are now) or None (the run's own: from config.json)."""
    return _policies().get(key)


@functools.cache
def _policies() -> dict[str, str]:
    """{config.json's key: its field's resume policy}, for TrainConfig's fields and those of its groups without
    prefix (whose keys are their fields' names)."""
    hints = typing.get_type_hints(TrainConfig)
    owners = [TrainConfig, *(hints[name] for name in flat_groups(TrainConfig))]
    return {f.name: f.metadata["resume"] for owner in owners for f in dataclasses.fields(owner)
            if "resume" in f.metadata}


def process_options(config: TrainConfig) -> dict[str, Any]:
    """This process's own options (resume policy "process"), by config.json's key."""
    return {key: option_value(config, key) for key, policy in _policies().items() if policy == "process"}


def option_value(config: Any, key: str) -> Any:
    """The value of config.json's `key` ("steps", "mcmc.cap_max", "appearance_lr": a key of a group without
    prefix is its field's name) in `config`."""
    owner, _, name = key.rpartition(".")
    if owner:
        return option_value(getattr(config, owner), name)
    group = _flat_owner(type(config), name)
    return getattr(getattr(config, group) if group else config, name)


def with_options(config: TrainConfig, **values: Any) -> TrainConfig:
    """`config` with the options of config.json's top-level keys `values` replaced (those of groups without prefix
    by their own names: with_options(config, surface=True); a prefixed group such as mcmc is replaced whole)."""
    top, groups = _by_group(values)
    top.update({group: dataclasses.replace(getattr(config, group), **changed) for group, changed in groups.items()})
    return dataclasses.replace(config, **top)


def config_of(**values: Any) -> TrainConfig:
    """A configuration made in one go from options named as config.json and the command line name them (a script's
    short form: config_of(data=scene, steps=500, surface=True) is TrainConfig(data=scene, steps=500,
    surface_terms=SurfaceOptions(surface=True)))."""
    top, groups = _by_group(values)
    defaults = {f.name: f.default_factory() for f in dataclasses.fields(TrainConfig) if f.name in groups}
    top.update({group: dataclasses.replace(defaults[group], **changed) for group, changed in groups.items()})
    return TrainConfig(**top)


def _by_group(values: dict[str, Any]) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """`values` split into TrainConfig's own fields and those of each group without prefix."""
    top: dict[str, Any] = {}
    groups: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        group = _flat_owner(TrainConfig, key)
        if group:
            groups.setdefault(group, {})[key] = value
        else:
            top[key] = value
    return top, groups


def _flat_owner(cls: type, name: str) -> str | None:
    """The group without prefix of `cls` that holds the field `name`, or None (a field of `cls` itself)."""
    return _flat_owners(cls).get(name) if dataclasses.is_dataclass(cls) else None


@functools.cache
def _flat_owners(cls: type) -> dict[str, str]:
    """{a field of a group without prefix of `cls`: that group}."""
    hints = typing.get_type_hints(cls)
    return {f.name: group for group in flat_groups(cls) for f in dataclasses.fields(hints[group])}


# (init scale, init opacity) per strategy: the MCMC paper's code, and 3DGS's for its ADC.
INITIAL_GAUSSIANS = {"mcmc": (0.1, 0.5), "adc": (1.0, 0.1)}
BUDGET_RESOLUTION_START = 0.25  # --budget trains coarse to fine from a quarter of the image size
RESOLUTION_FULL_AT = 0.4  # ... reaching full size at 40% of the steps, unless --budget chooses
_UNITS = {"s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


def budget_seconds(text: str) -> float:
    """Seconds of a --budget: '10m', '90s', '1.5h', '2min' or a plain number of minutes."""
    value = str(text).strip().lower()
    unit = next((u for u in sorted(_UNITS, key=len, reverse=True) if value.endswith(u)), None)
    number = value[:-len(unit)] if unit else value
    try:
        seconds = float(number) * _UNITS[unit or "m"]
    except ValueError:
        seconds = float("nan")
    if not (seconds > 0 and seconds < float("inf")):
        raise MCSplatError(f"--budget {text!r} is not a duration: give minutes ('10'), or a number with s, m or h "
                           "('90s', '10m', '1.5h')")
    return seconds


def flat_options(options: dict, prefix: str = "") -> dict[str, Any]:
    """config.json's nesting as keys: {"mcmc": {"cap_max": 5}} -> {"mcmc.cap_max": 5}."""
    flat = {}
    for key, value in options.items():
        if isinstance(value, dict):
            flat.update(flat_options(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def named_options(args: Sequence[str]) -> frozenset[str]:
    """The options the arguments of `mcsplat train` name, as config.json's keys: --steps 60 -> steps,
    --no-pose-opt -> pose_opt, --mcmc.cap-max=5 -> mcmc.cap_max."""
    known = flat_options(to_jsonable(TrainConfig(data=Path("."))))
    named = set()
    for arg in args:
        if not arg.startswith("--"):
            continue
        key = arg[2:].split("=", 1)[0].replace("-", "_")
        owner, dot, name = key.rpartition(".")
        if key not in known and name.startswith("no_"):  # --no-pose-opt, --mcmc.no-auto-cap
            key = owner + dot + name[3:]
        named.add(key)
    return frozenset(named)


def options_given(config: TrainConfig) -> frozenset[str]:
    """The options the command line named (config.named), as config.json's keys. A configuration made in Python names
    none: it holds every option, so nothing tells which were meant (a script resuming a run with the object it
    started it with, its steps since scaled, means no change)."""
    return config.named or frozenset()


def to_jsonable(config: Any) -> Any:
    """config.json's form of a configuration (or any of its values): a group of options without prefix keeps its
    options beside the others, as the command line gives them."""
    if dataclasses.is_dataclass(config):
        record: dict[str, Any] = {}
        flat = flat_groups(type(config))
        for f in dataclasses.fields(config):
            if not f.metadata.get("saved", True):
                continue
            value = to_jsonable(getattr(config, f.name))
            if f.name in flat:
                record.update(value)
            else:
                record[f.name] = value
        return record
    if isinstance(config, Path):
        return str(config)
    if isinstance(config, (list, tuple)):
        return [to_jsonable(v) for v in config]
    return config


# The option groups config.json nests (--mcmc.cap-max is {"mcmc": {"cap_max": ...}}).
NESTED_GROUPS = {"model": ModelConfig, "optim": OptimConfig, "mcmc": MCMCConfig, "adc": ADCConfig}


def from_jsonable(data: dict, source: str = "config.json") -> TrainConfig:
    """Rebuild a TrainConfig from config.json (unknown keys are an error: the file belongs to another version; so is
    a value of the wrong type or out of range: the file was edited by hand). `source` names where the options were
    read in the errors (blocks.json keeps them as its "training")."""
    return checked_dataclass(TrainConfig, data, source, nested=NESTED_GROUPS)
