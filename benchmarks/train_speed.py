"""Training speed: median ms per full training step and the share of each phase, one JSON line per configuration.

    .venv/bin/python benchmarks/train_speed.py                                  # 10k/100k/300k x 1 and 2 threads
    .venv/bin/python benchmarks/train_speed.py --sizes 100000 --threads 2 --repeats 5
    .venv/bin/python benchmarks/train_speed.py --device cuda                    # skips cleanly without CUDA
    .venv/bin/python benchmarks/train_speed.py --sizes 100000 --threads 2 --updates auto plain   # fused Adam or not

A step is the trainer's own (mcsplat.step.Step): render a lego 400x400 training view, 0.8 L1 + 0.2 D-SSIM +
the MCMC regularizers, backward, one Adam step per parameter, strategy.step_post_optimizer (SGLD noise; relocation
every 100 steps). The same step is also run with a PhaseClock, which the step tells where it is (StepPhases) and
which reads the clock after a device sync between phases; render() runs a render path (mcsplat.render.paths) whose
three stages are the kernel path's, wrapped with timers:

    projection           activations, EWA projection, culling, tile rectangles, SH colours (project_and_shade)
    binning              (tile, depth) keys, sort, tile ranges (bin_gaussians)
    composite_forward    the Warp forward kernels (CompositeFunction.apply)
    loss                 L1 + SSIM + regularizers, forward
    backward_loss        from loss.backward() until the gradient of the image is complete (SSIM/L1 backward)
    backward_composite   CompositeFunction.backward (the hand-written Warp backward kernels)
    backward_projection  the rest of the backward: projection, SH and activations (torch autograd)
    optimizer            the six Adam steps and zero_grad (with the fused update, optim/fused_projection.py, the
                         projection's backward too: "backward_projection" keeps autograd's activation backwards)
    strategy             step_post_backward + step_post_optimizer (noise), plus one refine step / 100 (amortised)
    other                the rest (learning-rate update, image to float, render()'s glue, the train PSNR,
                         instrumentation)

With --baseline the same process also times plain steps through the render path as it was before the CPU kernels
(torch projection, SH and binning, scalar Warp compositing: `mcsplat.render.paths.TORCH_BASELINE_PATH`), on the
same model and views, and reports the ratio.

Each configuration runs in a fresh subprocess so that its peak memory (ru_maxrss) is its own. The Gaussians are not
the random initialisation (tiny splats: an unrealistically cheap step) but a calibrated stand-in for a trained model,
see `realistic_model`; --scene-model init times the MCMC random initialisation instead.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
import tyro

import _common as C
from mcsplat.camera import Camera
from mcsplat.config import TrainConfig
from mcsplat.data import View
from mcsplat.gaussians import GaussianModel
from mcsplat.optim import PlainUpdate, make_optimizers, means_lr_at, update_for
from mcsplat.optim.fused_projection import FusedProjectionAdam
from mcsplat.render import RenderResult
from mcsplat.render.composite.function import CompositeFunction
from mcsplat.render.paths import TORCH_BASELINE_PATH, RenderPath, current_render_path, use_render_path
from mcsplat.strategy.adc import ADCConfig, ADCStrategy
from mcsplat.strategy.mcmc import MCMCConfig, MCMCStrategy
from mcsplat.planning import Plan
from mcsplat.run.folder import RunDir
from mcsplat.step import Step

PHASES = ("projection", "binning", "composite_forward", "loss", "backward_loss", "backward_composite",
          "backward_projection", "optimizer", "strategy", "other")
BALL_RADIUS = 1.25       # about the half-extent of the lego model, centred on the world origin like the lego
BASE_SCALE = 0.007       # rasterizer.py's calibration: ~33 composited Gaussians per pixel at 100k, 400x400
NUM_VIEWS = 16           # training views cycled through (evenly spaced over the 100 lego views)
TOTAL_STEPS = 30_000     # the learning-rate schedule the steps are taken from
REFINE_EVERY = 100
DEAD_FRACTION = 0.01     # Gaussians made dead before each timed refine step (so relocation has work)


@dataclass(frozen=True)
class Options:
    """Training speed: ms per training step and the share of each phase."""

    sizes: tuple[int, ...] = (10_000, 100_000, 300_000)
    """Numbers of Gaussians."""
    threads: tuple[int, ...] = (1, 2)
    """CPU threads (ignored on CUDA)."""
    device: str = "cpu"
    """cpu or cuda."""
    scene: str = "lego"
    """lego (shared data) or a scene folder."""
    data_root: str = str(C.DATA_ROOT)
    """The shared data folder."""
    scene_model: Literal["realistic", "init", "sfm"] = "realistic"
    """realistic: calibrated stand-in for a trained model; init: the MCMC random init; sfm: the scene's SfM points
    (--sizes is then ignored)."""
    downscale: int = 1
    """Image downscale factor of the scene."""
    model_from: str | None = None
    """A trained run folder of --scene: time the steps of its model (--sizes is then ignored)."""
    strategy: Literal["mcmc", "adc"] = "mcmc"
    """The densification strategy of the steps."""
    warmup: int = 3
    """Untimed steps first."""
    repeats: int = 10
    """Instrumented steps (medians)."""
    plain: int = 5
    """Un-instrumented trainer steps (the 'step ms' figure)."""
    refines: int = 3
    """Timed refine steps (0: leave them out)."""
    seed: int = 0
    """Random seed of the model and of the refine steps."""
    baseline: bool = False
    """Also time plain steps through the pre-kernel render path, in the same process."""
    builds: tuple[str, ...] = ("native",)
    """CPU kernel builds to time, each in its own processes: native (this host's), or an LLVM CPU name (znver3: AVX2
    without AVX-512), optionally :LANES (4, 8, 16), e.g. znver3:8."""
    updates: tuple[Literal["auto", "plain", "fused"], ...] = ("auto",)
    """The step's parameter update, each in its own processes: auto (the trainer's: on the CPU the projection's
    backward fused with Adam, optim/fused_projection.py; plain on CUDA until measured), plain (autograd finishes every
    gradient, then Adam) or fused (on CUDA too: the Warp kernel)."""
    rounds: int = 1
    """Times each configuration runs, the builds taking turns (medians over rounds: results.md shows each run)."""
    out: str | None = None
    """Results folder (default benchmarks/results/train_speed)."""


# --------------------------------------------------------------------------------------------------- the scene
def realistic_model(n: int, seed: int = 0) -> GaussianModel:
    """n Gaussians in a ball of radius 1.25 around the origin, sized like a trained model's.

    This is benchmarks/rasterizer.py's calibrated scene, scaled by 1.25 in space so that under the lego cameras
    (distance 4.03, focal 1.39 x width) it projects as rasterizer.py's scene does under its own camera: at 100k and
    400x400 about 33 Gaussians are composited per pixel (the reference configuration of the rasterizer targets).
    Scales are log-normal around 0.00875 x (100k / n)^(1/3) (finer Gaussians as there are more of them), rotations
    random, opacities uniform in [0.05, 0.65], SH degree 3 with small higher bands.
    """
    g = torch.Generator().manual_seed(seed)
    direction = F.normalize(torch.randn(n, 3, generator=g), dim=-1)
    means = direction * torch.rand(n, 1, generator=g) ** (1 / 3) * BALL_RADIUS
    base = BASE_SCALE * BALL_RADIUS * (100_000 / n) ** (1 / 3)
    log_scales = math.log(base) + 0.3 * torch.randn(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g) * 0.6 + 0.05
    sh0 = torch.randn(n, 1, 3, generator=g) * 0.5
    shN = torch.randn(n, 15, 3, generator=g) * 0.05
    return GaussianModel(means, log_scales, quats, torch.logit(opacities), sh0, shN)


def init_model(n: int, seed: int = 0) -> GaussianModel:
    """The MCMC random initialisation of a Blender scene (cube [-1.3, 1.3]^3, 0.1 x kNN scales, opacity 0.5)."""
    return GaussianModel.random_init(1.0, blender=True, num_points=n, generator=torch.Generator().manual_seed(seed))


def training_views(scene, size: int | None = None, count: int = NUM_VIEWS) -> tuple[list[Camera], list[torch.Tensor]]:
    """`count` evenly spaced training views: cameras and uint8 images, resized to size x size when given."""
    views = scene.train[:: max(1, len(scene.train) // count)][:count]
    cameras, images = [], []
    for view in views:
        camera, image = view.camera, view.image
        if size is not None and (size, size) != (camera.width, camera.height):
            camera = camera.scaled(size, size)
            x = image.permute(2, 0, 1)[None].float()
            x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
            image = x[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).contiguous()
        cameras.append(camera)
        images.append(image)
    return cameras, images


@dataclass
class Bench:
    """Everything one training step needs, set up as the trainer sets it up."""

    model: GaussianModel
    optimizers: dict
    strategy: object
    views: list[View]
    background: tuple
    radius: float
    device: torch.device
    config: TrainConfig
    update: object  # optim.ParameterUpdate

    @classmethod
    def make(cls, model: GaussianModel, scene, cameras, images, device: str, strategy: str = "mcmc",
             update: str = "auto") -> "Bench":
        device = torch.device(device)
        model = model.to(device)
        # SH degree 3 from the first step timed (sh_increase_every 1), the learning rates of a 30,000-step run.
        config = TrainConfig(data=scene.root, steps=TOTAL_STEPS, sh_increase_every=1, strategy=strategy)
        optimizers = make_optimizers(model, config.optim, scene.radius)
        generator = torch.Generator(device=device).manual_seed(0)
        n = model.num_gaussians
        if strategy == "mcmc":  # at the cap, as in a run that has grown to its budget: refine steps only relocate
            strat = MCMCStrategy(MCMCConfig(cap_max=n), scene.radius, generator)
        else:
            strat = ADCStrategy(ADCConfig(cap_max=n), scene.radius, generator)
        views = [View(camera, image, f"view{i}") for i, (camera, image) in enumerate(zip(cameras, images))]
        chosen = {"auto": update_for(device), "plain": PlainUpdate(), "fused": FusedProjectionAdam()}[update]
        return cls(model, optimizers, strat, views, tuple(scene.background), scene.radius, device, config, chosen)

    def camera(self, i: int) -> Camera:
        return self.views[i % len(self.views)].camera

    def lr(self, step: int) -> float:
        return means_lr_at(step, TOTAL_STEPS, self.config.optim, self.radius)


def step_numbers(start: int = 1001):
    """0-based step numbers inside the refine window that are not refine steps (1001..1099, 1101, ...)."""
    step = start
    while True:
        if step % REFINE_EVERY:
            yield step
        step += 1


# ------------------------------------------------------------------------------------------------------- the step
class StepMarks:
    """The trainer's StepPhases that only keeps the last render's tile pairs (read after the step: on a GPU, reading
    them in it would make the step wait where the trainer's does not)."""

    def __init__(self) -> None:
        self.bins = None

    def rendered(self, result: RenderResult) -> None:
        self.bins = result.bins

    @property
    def pairs(self) -> int:
        return 0 if self.bins is None else self.bins.num_pairs

    def lap(self, phase: str) -> None:
        pass


class PhaseClock(StepMarks):
    """Times the phases of the trainer's step: the step marks its phases (lap), the render path's three
    stages are wrapped with timers (`timed_path`), and every reading of the clock follows a device synchronisation."""

    def __init__(self, device: torch.device):
        super().__init__()
        self.device = device
        self.seconds: dict[str, float] = {}
        self.last = 0.0
        self.captured: dict = {}  # the last render's bins and compositing inputs (for the per-pixel statistics)

    def start(self) -> None:
        self.seconds = dict.fromkeys(("other", "render", "loss", "backward", "reduce", "optimizer", "strategy",
                                      "projection", "binning", "composite_forward", "backward_composite"), 0.0)
        self.image_grad_at = None
        self.backward_start = None
        self.last = C.now(self.device)

    def lap(self, phase: str) -> None:
        t = C.now(self.device)
        self.seconds[phase] += t - self.last
        self.last = t
        if phase == "backward":
            self.backward_loss = (self.image_grad_at or self.backward_start) - self.backward_start

    def rendered(self, result: RenderResult) -> None:
        """Mark when d loss / d image is complete: the end of the loss backward, the start of the composite's."""
        super().rendered(result)

        def hook(grad):
            self.image_grad_at = C.now(self.device)
        result.rgb.register_hook(hook)
        self.backward_start = self.last

    def add(self, phase: str, seconds: float) -> None:
        self.seconds[phase] += seconds

    def phases(self) -> dict[str, float]:
        """Seconds per entry of PHASES, plus 'total'. The backward splits at the image-gradient mark; whatever
        render() does besides its three timed pieces (input checks, the depth division) counts as 'other'."""
        s = self.seconds
        out = {p: s[p] for p in ("projection", "binning", "composite_forward", "loss", "backward_composite",
                                 "optimizer", "strategy")}
        out["backward_loss"] = self.backward_loss
        out["backward_projection"] = s["backward"] - self.backward_loss - s["backward_composite"]
        out["other"] = (s["other"] + s["reduce"] + s["render"] - s["projection"] - s["binning"]
                        - s["composite_forward"])
        out["total"] = sum(s[p] for p in ("other", "reduce", "render", "loss", "backward", "optimizer", "strategy"))
        return out

    def timed_path(self, path: RenderPath) -> RenderPath:
        """`path` with each stage timed (the composite's forward and backward apart)."""
        clock = self

        def timed(phase, fn, keep=None):
            def wrapper(*args, **kwargs):
                t0 = C.now(clock.device)
                out = fn(*args, **kwargs)
                clock.add(phase, C.now(clock.device) - t0)
                if keep:
                    clock.captured[keep] = out
                return out
            return wrapper

        class TimedComposite(CompositeFunction):
            @staticmethod
            def backward(ctx, *grads):
                t0 = C.now(clock.device)
                out = CompositeFunction.backward(ctx, *grads)
                clock.add("backward_composite", C.now(clock.device) - t0)
                return out

        def composite(*args):
            t0 = C.now(clock.device)
            out = TimedComposite.apply(*args)
            clock.add("composite_forward", C.now(clock.device) - t0)
            clock.captured["composite_inputs"] = args
            return out

        return RenderPath(project=timed("projection", path.project), bin=timed("binning", path.bin, keep="bins"),
                          composite=composite)


def bench_step(b: Bench, step: int, i: int, marks: StepMarks | None = None) -> int:
    """One training step through the trainer's own Step on view i; returns its tile pairs. With a
    PhaseClock (and its timed render path in force) the phases are timed."""
    marks = marks or StepMarks()
    if isinstance(marks, PhaseClock):
        marks.start()
    one_step = Step(b.model, b.optimizers, b.strategy, b.config, b.radius, b.background, b.device, phases=marks,
                    update=b.update)
    one_step(step, b.views[i % len(b.views)], Plan.literal(b.config))
    return marks.pairs


def refine_seconds(b: Bench, repeats: int, seed: int = 0) -> list[float]:
    """Duration of step_post_optimizer on refine steps, with DEAD_FRACTION of the Gaussians made dead first."""
    g = torch.Generator().manual_seed(seed)
    times = []
    for r in range(repeats):
        n = b.model.num_gaussians
        with torch.no_grad():
            dead = torch.randperm(n, generator=g)[: max(1, int(DEAD_FRACTION * n))].to(b.device)
            b.model.params["opacity_logits"][dead] = math.log(0.003 / 0.997)
        step = 1100 + REFINE_EVERY * r
        t0 = C.now(b.device)
        b.strategy.step_post_optimizer(step, b.model, b.optimizers, b.lr(step + 1))
        times.append(C.now(b.device) - t0)
    return times


def composited_per_pixel(clock: PhaseClock, width: int) -> float | None:
    """Gaussians composited per pixel in the last timed render, by rasterizer.py's sampling (square images only;
    None otherwise)."""
    from rasterizer import _per_pixel_counts
    bins, args = clock.captured.get("bins"), clock.captured.get("composite_inputs")
    if bins is None or args is None or bins.tiles_x != bins.tiles_y:
        return None
    return _per_pixel_counts(bins, [t.detach() for t in args[:3]], width)[1]

# ------------------------------------------------------------------------------------------- one configuration
def run_one(cfg: dict) -> dict:
    """Measure one configuration in this process (the parent runs it in a fresh subprocess)."""
    device = cfg["device"]
    C.set_threads(cfg["threads"])
    scene = C.load(cfg["data"], cfg.get("downscale", 1))
    cameras, images = training_views(scene)
    baseline_rss = C.current_rss_mb()  # imports and the scene's images, before any Gaussian exists
    if cfg.get("model_from"):  # a trained run's model: the step a real capture has late in its run
        state = RunDir(cfg["model_from"]).read_checkpoint()["model"]
        model = GaussianModel.from_state_dict(state)
    elif cfg["scene_model"] == "sfm":  # the scene's own SfM points, as `mcsplat train` initialises a capture
        if scene.points is None:
            sys.exit(f"train_speed: {cfg['data']} has no SfM points for --scene-model sfm")
        model = GaussianModel.from_points(scene.points, scene.point_colors)
    else:
        builder = realistic_model if cfg["scene_model"] == "realistic" else init_model
        model = builder(cfg["gaussians"], cfg["seed"])
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    b = Bench.make(model, scene, cameras, images, device, cfg["strategy"], cfg.get("update", "auto"))
    steps = step_numbers()
    view = 0
    for _ in range(cfg["warmup"]):
        bench_step(b, next(steps), view)
        view += 1
    phases: dict[str, list[float]] = {p: [] for p in PHASES + ("total",)}
    pairs = []
    clock = PhaseClock(b.device)
    with use_render_path(clock.timed_path(current_render_path())):
        for _ in range(cfg["repeats"]):
            pairs.append(bench_step(b, next(steps), view, clock))
            view += 1
            for key, seconds in clock.phases().items():
                phases[key].append(seconds)
    composited = composited_per_pixel(clock, b.camera(view - 1).width)
    plain = []
    for _ in range(cfg["plain"]):
        t0 = C.now(device)
        bench_step(b, next(steps), view)
        plain.append(C.now(device) - t0)
        view += 1
    peak_rss = C.peak_rss_mb()  # before the baseline's steps, which need more memory
    baseline = []
    if cfg.get("baseline"):
        with use_render_path(TORCH_BASELINE_PATH):
            for _ in range(cfg["plain"]):
                t0 = C.now(device)
                bench_step(b, next(steps), view)
                baseline.append(C.now(device) - t0)
                view += 1
    refine = refine_seconds(b, cfg["refines"], cfg["seed"]) if cfg["refines"] else []

    ms = {p: C.median(v) * 1000.0 for p, v in phases.items()}
    refine_extra_ms = max(0.0, C.median(refine) * 1000.0 - ms["strategy"]) if refine else 0.0
    ms["strategy"] += refine_extra_ms / REFINE_EVERY
    phase_sum = sum(ms[p] for p in PHASES)
    ranked = sorted(PHASES, key=lambda p: -ms[p])
    record = {
        "benchmark": "train_speed", "device": device if device != "cpu" else f"cpu ({C.cpu_name()})",
        "gaussians": b.model.num_gaussians, "image": f"{b.camera(0).width}x{b.camera(0).height}",
        "threads": cfg["threads"] if device == "cpu" else None,
        "scene_model": f"run {cfg['model_from']}" if cfg.get("model_from") else cfg["scene_model"],
        "strategy": cfg["strategy"], "build": cfg.get("build", "native"),
        "update": f"{cfg.get('update', 'auto')} ({type(b.update).__name__})",
        "step_ms": round(C.median(plain) * 1000.0 + refine_extra_ms / REFINE_EVERY, 1) if plain else None,
        "instrumented_step_ms": round(ms["total"] + refine_extra_ms / REFINE_EVERY, 1),
        "baseline_step_ms": round(C.median(baseline) * 1000.0, 1) if baseline else None,
        "speedup_over_baseline": round(C.median(baseline) / C.median(plain), 2) if baseline and plain else None,
        "phases_ms": {p: round(ms[p], 2) for p in PHASES},
        "shares": {p: round(ms[p] / phase_sum, 4) for p in PHASES},
        "dominant": ranked[0], "dominant_share": round(ms[ranked[0]] / phase_sum, 3),
        "dominant_over_next": round(ms[ranked[0]] / max(ms[ranked[1]], 1e-9), 2), "next": ranked[1],
        "compositing_share": round((ms["composite_forward"] + ms["backward_composite"]) / phase_sum, 3),
        "backward_share": round(sum(ms[p] for p in PHASES if p.startswith("backward")) / phase_sum, 3),
        "refine_step_ms": round(C.median(refine) * 1000.0, 1) if refine else None,
        "tile_pairs": int(C.median(pairs)),
        "composited_per_pixel": round(composited, 1) if composited is not None else None,
        "warmup": cfg["warmup"], "repeats": cfg["repeats"], "plain_repeats": cfg["plain"], "refines": cfg["refines"],
    }
    if device.startswith("cuda"):
        record["peak_cuda_mb"] = round(torch.cuda.max_memory_allocated() / 2 ** 20, 1)
    else:
        record["peak_rss_mb"] = round(peak_rss, 1)
        record["rss_before_model_mb"] = round(baseline_rss, 1) if baseline_rss is not None else None
    return record


def build_environment(build: str) -> dict[str, str]:
    """The environment of a worker that runs the CPU kernels built as `build` says: "native" (this host's), or an
    LLVM CPU name (znver3: AVX2, no AVX-512), optionally with ":LANES" (the SIMD kernels' vector width)."""
    target, _, lanes = build.partition(":")
    env = {**os.environ, "MCSPLAT_CPU_TARGET": target}
    if lanes:
        env["MCSPLAT_SIMD_LANES"] = lanes
    return env


def run_in_subprocess(cfg: dict) -> dict:
    proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(cfg)], stdout=subprocess.PIPE, text=True,
                          env=build_environment(cfg.get("build", "native")))
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        sys.exit(f"train_speed: the configuration {cfg} failed (exit {proc.returncode})")
    return json.loads(lines[-1])


# ------------------------------------------------------------------------------------------------ the reports
def label(r: dict) -> str:
    return (C.human(r["gaussians"]) + (f" / {r['threads']}t" if r.get("threads") else "")
            + (f" / {r['build']}" if r.get("build", "native") != "native" else ""))


def markdown(records: list[dict], info: dict, args) -> str:
    cols = [("Gaussians", "gaussians", ""), ("threads", "threads", "")]
    if any(r.get("build", "native") != "native" for r in records):
        cols += [("build", "build", "")]
    if len({r.get("update") for r in records}) > 1:
        cols += [("update", "update", "")]
    cols += [("step ms", "step_ms", ".1f")]
    if records and records[0].get("baseline_step_ms"):
        cols += [("baseline ms", "baseline_step_ms", ".1f"), ("speed-up", "speedup_over_baseline", ".2f")]
    cols += [(p.replace("_", " "), p, lambda r, p=p: f"{r['phases_ms'][p]:.1f} ({100 * r['shares'][p]:.0f}%)")
             for p in PHASES]
    mem = "peak_cuda_mb" if records and "peak_cuda_mb" in records[0] else "peak_rss_mb"
    cols += [("peak MB", mem, ".0f"), ("composited/px", "composited_per_pixel", ".1f")]
    lines = [f"# Training speed ({records[0]['device'] if records else args.device})", "",
             f"Machine: {C.machine_line(info)}. Commit {C.git_commit()}, {C.timestamp()}.", "",
             f"{Path(args.scene).name} {records[0]['image'] if records else ''}, scene model "
             f"`{records[0]['scene_model'] if records else args.scene_model}`, strategy "
             f"`{args.strategy}`; medians of {args.repeats} instrumented steps after {args.warmup} warm-up steps; "
             f"'step ms' is the median of {args.plain} un-instrumented trainer steps; the strategy column includes "
             f"one refine step per {REFINE_EVERY} steps. Phase ms (share of the phase sum).", "",
             C.markdown_table(records, cols), ""]
    for r in records:
        lines.append(f"- {label(r)}: **{r['dominant'].replace('_', ' ')}** dominates with "
                     f"{100 * r['dominant_share']:.0f}% of the step, {r['dominant_over_next']:.1f}x the next phase "
                     f"({r['next'].replace('_', ' ')}); compositing forward + backward "
                     f"{100 * r['compositing_share']:.0f}%, the whole backward {100 * r['backward_share']:.0f}%; "
                     f"a refine step costs {r['refine_step_ms']} ms.")
    return "\n".join(lines) + "\n"


def plot(records: list[dict], path: Path) -> bool:
    plt = C.pyplot()
    if plt is None or not records:
        return False
    fig, ax = plt.subplots(figsize=(max(7.0, 1.1 * len(records) + 3.5), 4.8))
    x = range(len(records))
    bottom = [0.0] * len(records)
    colors = plt.get_cmap("tab10").colors
    for k, phase in enumerate(PHASES):
        shares = [100 * r["shares"][phase] for r in records]
        ax.bar(x, shares, bottom=bottom, color=colors[k % 10], label=phase.replace("_", " "))
        bottom = [b + s for b, s in zip(bottom, shares)]
    for i, r in enumerate(records):
        ax.text(i, 101, f"{r['step_ms'] or r['instrumented_step_ms']:.0f} ms", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(list(x), [label(r) for r in records])
    ax.set_ylabel("share of the training step (%)")
    ax.set_ylim(0, 110)
    ax.set_title(f"Training step phases (median ms on top), lego {records[0]['image']}\n{records[0]['device']}",
                 fontsize=9)
    ax.legend(loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def main() -> None:
    if sys.argv[1:2] == ["--worker"]:  # one configuration, in the process run_in_subprocess() started
        C.emit(run_one(json.loads(sys.argv[2])))
        return
    args = tyro.cli(Options, description=__doc__)
    C.cuda_or_exit(args.device, "train_speed")
    out = C.results_dir("train_speed", args.out)
    info = C.machine(args.device)
    load = C.warn_if_busy()
    threads = sorted(set(args.threads)) if args.device == "cpu" else [None]
    records = []
    sizes = [0] if args.scene_model == "sfm" or args.model_from else args.sizes  # the points or the run fix it
    runs = [(n, t, build, update) for _ in range(args.rounds) for n in sizes for t in threads for build in args.builds
            for update in args.updates]
    for n, t, build, update in runs:
        cfg = {"gaussians": n, "threads": t, "device": args.device, "scene_model": args.scene_model, "build": build,
               "update": update,
               "strategy": args.strategy, "warmup": args.warmup, "repeats": args.repeats, "plain": args.plain,
               "refines": args.refines, "seed": args.seed, "baseline": args.baseline,
               "downscale": args.downscale, "model_from": args.model_from,
               "data": str(C.scene_path(args.scene, args.data_root))}
        started = time.perf_counter()
        record = run_in_subprocess(cfg)
        record.update(wall_seconds=round(time.perf_counter() - started, 1), load_average_before=load,
                      machine=info, commit=C.git_commit(), date=C.timestamp())
        C.emit(record)
        records.append(record)
    C.write_results(out, records, markdown(records, info, args))
    if plot(records, out / "phases.png"):
        print(f"wrote {out / 'phases.png'}", file=sys.stderr)


if __name__ == "__main__":
    main()
