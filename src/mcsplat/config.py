"""What the user asked of a training run: frozen dataclasses that tyro turns into the `mcsplat train` options.

The configuration is one value that nothing changes once it is made (`dataclasses.replace` derives another). What a
run decides as it goes (its steps, the schedules fitted to them, the cap and growth rate, the number of processes) is
its plan (mcsplat.planning), made from this and handed to the step and the strategy beside it.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Sequence

import tyro

from .config_types import checked_dataclass, option_types
from .errors import MCSplatError
from .optim import OptimConfig
from .strategy.adc import ADCConfig
from .strategy.mcmc import MCMCConfig

# Options that only affect how this process runs: on --resume they come from the command line, the rest from
# the run's saved configuration (steps included: the learning-rate schedule depends on it).
PROCESS_OPTIONS = ("eval_every", "save_every", "save_every_minutes", "quiet", "threads", "device", "viewer", "port",
                   "host", "viewer_origin", "dist_timeout")


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
class TrainConfig:
    """Train a 3D Gaussian Splatting scene with the MCMC method (or the 3DGS ADC baseline)."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATA")]
    """Scene folder: COLMAP, NeRF/Blender transforms or LLFF poses_bounds (auto-detected)."""
    out: Path | None = None
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
    masks: str = "auto"
    """Pixels the loss leaves out: 'auto' takes the scene's masks/ folder when it has one (a PNG per image,
    masks/<image name>.png, black: left out), 'none' ignores it, 'alpha' takes the images' alpha channel, or give a
    folder. Evaluation reports masked PSNR / SSIM beside the plain ones."""
    invert_masks: bool = False
    """Masks are white where the pixel is left out (and black where it is kept)."""
    depths: str = "none"
    """Depth maps loaded onto the views, for --depth-loss: 'none', 'auto' (beside each photo as <photo
    stem>_depth.npy / .png, or the scene's depths/ folder) or a folder of <image name>.npy / .png. A view without one
    has none."""
    depth_encoding: Literal["metric", "nerf-synthetic"] = "metric"
    """metric: .npy floats, or 16-bit PNG steps of --depth-png-step, in the capture's units; nerf-synthetic: its
    8-bit renders (8 (1 - R/255) along the ray, R = 0: no object)."""
    depth_measure: Literal["z", "ray"] = "z"
    """What a metric depth map measures: z (along the optical axis) or ray (from the camera along the pixel's ray)."""
    depth_png_step: float = 0.001
    """A 16-bit PNG depth map's step in the capture's units (0.001: millimetres of a capture in metres)."""
    depth_loss: Literal["none", "metric", "relative", "disparity"] = "none"
    """Hold the rendered depth to the --depths maps: metric (a sensor's depths in the scene's units; maps in other
    units are refused), relative (a monocular model's depth, its scale and shift fitted to the render in each view)
    or disparity (the same for inverse depth: MiDaS, Depth Anything). The mean relative error where a map has a
    depth (docs/training.md)."""
    depth_weight: float = 0.1
    """Weight of --depth-loss (on the mean relative depth error) ..."""
    depth_from: float = 0.0
    """... from this share of the steps on ..."""
    depth_final: float = 1.0
    """... going linearly to this share of itself at the last step."""
    sparse_depth: float = 0.0
    """Weight of sparse depth from the SfM points (COLMAP scenes): the rendered depth at the pixel of each point an
    image saw held to the point's depth (mean relative error); 0: off. 0.1 is a start (docs/training.md) ..."""
    sparse_depth_from: float = 0.5
    """... from this share of the steps on (from the start it cost the bird 1.2 dB, from half way 0.2) ..."""
    sparse_depth_final: float = 1.0
    """... going linearly to this share of itself at the last step."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """auto: CUDA when available, else CPU."""
    seed: int = 0
    """Random seed of the initialisation, the view order, relocation and noise."""
    threads: int | None = None
    """CPU threads (default: all cores)."""
    eval_every: int = 0
    """Evaluate on the test views every N steps (0: only at the end)."""
    save_every: int = 5000
    """Write a checkpoint every N steps (and on Ctrl-C or SIGTERM)."""
    save_every_minutes: float = 10.0
    """Also write one when this many minutes have passed since the last (0: off)."""
    resume: bool = False
    """Continue from the run directory's checkpoint."""
    overwrite: bool = False
    """Allow writing into a run directory that already holds a run (files are replaced, never deleted)."""
    quiet: bool = False
    """No progress bar or messages (for scripts); the final scores and the files written are still printed."""
    sh_increase_every: int = 1000
    """The active SH degree grows by one every N steps up to the model's degree."""
    ssim_weight: float = 0.2
    """Weight of D-SSIM in the loss; L1 gets the rest (the paper: 0.2)."""
    appearance: Literal["none", "affine", "bilateral-grid"] = "none"
    """Exposure / white-balance compensation: 'affine' learns a colour transform (3x3 + bias) per training image,
    'bilateral-grid' a 16x16x8 grid of them over the image and its brightness; applied to the render before the
    loss; renders and exports show the scene without it. Evaluation adds the compensated score (an affine transform
    of each test view fitted on its left half, its right half scored)."""
    appearance_lr: float = 0.003
    """Learning rate of the per-image transforms at the first step (3DGS's exposure rate, 0.01, was worse on a test
    capture with shifted colours: 24.3 against 24.8 dB) ..."""
    appearance_lr_final: float = 0.0003
    """... decaying log-linearly to this at the last step."""
    appearance_reg: float = 0.01
    """Weight of the pull of each image's transform toward identity (squared distance of A from I and of b from 0;
    for a bilateral grid, of its mean transform)."""
    appearance_grid_shape: tuple[int, int, int] = (16, 16, 8)
    """A bilateral grid's cells across the image, down it and over brightness (gsplat's 16 16 8, made for photos of
    about a megapixel: a grid holds 12 numbers a cell, so small images want a coarser one)."""
    appearance_grid_tv: float = 10.0
    """Weight of a bilateral grid's total variation (mean squared difference of neighbouring cells; gsplat's 10)."""
    pose_opt: bool = False
    """Learn a small rigid correction of each training image's pose with the scene (SfM poses of phone captures are
    slightly off); test views keep theirs."""
    pose_opt_lr: float = 1e-4
    """Adam learning rate of the corrections (rotation in radians, translation in scene radii). gsplat's 1e-5, set
    for 30,000 GPU steps, moves them too little in a few thousand: on the cup with its poses a degree off, 1,500 steps
    won back 18% of the PSNR lost at 1e-5, 66% at 1e-4, and overshot at 1e-3 ..."""
    pose_opt_reg: float = 1e-6
    """... and their weight decay."""
    surface: bool = False
    """Train for a surface a mesh can be made of (PGSR's single-view terms): Gaussians flattened toward surface
    elements, and from --surface-from on, the rendered normals held to the normals of the rendered (planar) depth.
    Costs one more compositing pass a step while the second term is on."""
    surface_flatten: float = 100.0
    """Weight of the mean smallest scale of the Gaussians a step sees, in scene radii (PGSR's 100)."""
    surface_normal: float = 0.015
    """Weight of the depth-normal consistency term (PGSR's 0.015), weighted per pixel by (1 - image gradient)^2."""
    surface_from: float = 0.23
    """The share of the steps after which the depth-normal term starts (PGSR: step 7,000 of 30,000)."""
    surface_distortion: float = 0.0
    """Weight of 2DGS's depth distortion (a pixel's Gaussians pulled together in inverse depth, in scene radii),
    from a tenth of the run on; 0: off. Costs one more compositing pass a step while it is on."""
    antialiased: bool = False
    """Mip-Splatting's 2D filter: a splat's opacity shrinks as the 0.3 px screen-space blur widens it, so fine
    detail keeps its weight when the scene is seen from farther away or at a lower resolution than it was trained
    at. The trained scene is always drawn this way (eval, viewer, renders; .spz records it)."""
    lpips_net: Literal["alex", "vgg"] = "vgg"
    """LPIPS backbone for the final metrics (the paper reports VGG)."""
    save_renders: bool = True
    """Write the final test renders as PNG."""
    viewer: bool = False
    """Serve a live web viewer of the training (needs `pip install mcsplat[viewer]`)."""
    port: int = 8080
    """Port of the live viewer."""
    host: str = "127.0.0.1"
    """Address the live viewer listens on; 0.0.0.0 exposes it to the network."""
    viewer_origin: tuple[str, ...] = ()
    """Web pages (host names or origins such as http://myhost:8080) allowed to connect to the viewer besides its own
    page: where it is reached under a name, or through a proxy."""
    dist_timeout: float = 600.0
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
                  (self.depth_png_step > 0, "--depth-png-step must be positive (0.001: millimetres of a capture in "
                                            "metres)"),
                  (self.depth_loss == "none" or self.depths != "none",
                   f"--depth-loss {self.depth_loss} reads depth maps, and --depths is 'none': give --depths auto "
                   "(beside the photos, or the scene's depths/) or the folder that holds them"),
                  (min(self.depth_weight, self.depth_final, self.sparse_depth, self.sparse_depth_final) >= 0
                   and 0 <= self.depth_from <= 1 and 0 <= self.sparse_depth_from <= 1,
                   "--depth-weight, --depth-final, --sparse-depth and --sparse-depth-final must be >= 0, "
                   "--depth-from and --sparse-depth-from within [0, 1]"),
                  (0.0 <= self.ssim_weight <= 1.0, "--ssim-weight must be in [0, 1]"),
                  (self.appearance_lr > 0 and self.appearance_lr_final > 0 and self.appearance_reg >= 0
                   and self.appearance_grid_tv >= 0,
                   "--appearance-lr and --appearance-lr-final must be positive, --appearance-reg and "
                   "--appearance-grid-tv 0 or more"),
                  (min(self.appearance_grid_shape) >= 2,
                   "--appearance-grid-shape needs at least 2 cells along each of its three axes"),
                  (self.surface_flatten >= 0 and self.surface_normal >= 0 and self.surface_distortion >= 0
                   and 0 <= self.surface_from <= 1,
                   "--surface-flatten, --surface-normal and --surface-distortion must be >= 0 and --surface-from "
                   "within [0, 1]"),
                  (self.pose_opt_lr > 0 and self.pose_opt_reg >= 0,
                   "--pose-opt-lr must be positive, --pose-opt-reg 0 or more"),
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
        ignored = surface_options_ignored(self)
        if ignored:
            raise MCSplatError(f"{', '.join(ignored)}: the --surface-* options shape the loss terms of --surface, "
                               f"which this run trains without, so they would be ignored; add --surface, or leave them "
                               f"out")
        ignored = depth_options_ignored(self)
        if ignored:
            raise MCSplatError(f"{', '.join(ignored)}: these shape a depth term this run trains without (--depth-loss "
                               f"none, --sparse-depth 0), so they would be ignored; add it, or leave them out")
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


def surface_options_ignored(config: TrainConfig) -> list[str]:
    """The --surface-* options the command line gave (`config.named`) to a new run without --surface, as it gave them
    (a resumed run's --surface is its own: run_dir compares the options given with it)."""
    if config.surface or config.resume or not config.named:
        return []
    return [f"--{name.replace('_', '-')} {getattr(config, name)}" for name in SURFACE_OPTIONS if name in config.named]


def depth_options_ignored(config: TrainConfig) -> list[str]:
    """The options of a depth term the command line gave to a new run without that term, as surface_options_ignored
    finds --surface's."""
    if config.resume or not config.named:
        return []
    off = (DENSE_DEPTH_OPTIONS if config.depth_loss == "none" else ()) + \
        (SPARSE_DEPTH_OPTIONS if config.sparse_depth == 0 else ())
    return [f"--{name.replace('_', '-')} {getattr(config, name)}" for name in off if name in config.named]


def non_finite_options(config: TrainConfig) -> list[str]:
    """The float options of `config` and of its model group that hold inf or nan, as the command line gives them (the
    groups optim, mcmc and adc check their own)."""
    found = []
    for group, prefix in ((config, ""), (config.model, "model.")):
        for name, hint in option_types(type(group)).items():
            value = getattr(group, name)
            if float in (hint, *typing.get_args(hint)) and isinstance(value, float) and not math.isfinite(value):
                found.append(f"--{prefix}{name.replace('_', '-')} {value}")
    return found


def process_options(config: TrainConfig) -> dict[str, Any]:
    """This process's own options (PROCESS_OPTIONS), as keyword arguments of `dataclasses.replace`."""
    return {name: getattr(config, name) for name in PROCESS_OPTIONS}


SURFACE_OPTIONS = ("surface_flatten", "surface_normal", "surface_from", "surface_distortion")  # --surface's terms
DENSE_DEPTH_OPTIONS = ("depth_weight", "depth_from", "depth_final")  # --depth-loss's
SPARSE_DEPTH_OPTIONS = ("sparse_depth_from", "sparse_depth_final")  # --sparse-depth's
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
    if dataclasses.is_dataclass(config):
        return {f.name: to_jsonable(getattr(config, f.name)) for f in dataclasses.fields(config)
                if f.metadata.get("saved", True)}
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
