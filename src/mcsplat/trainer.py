"""The training loop: schedules, progress, periodic evaluation, checkpoints and the run directory's outputs.

One step (SPEC 2, in gsplat's order, see strategy/mcmc.py for how the official code differs):
    render a training view -> loss = 0.8 L1 + 0.2 D-SSIM + strategy regularizers -> backward
    -> strategy.step_post_backward (ADC gradient statistics) -> Adam step for every parameter
    -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD noise; ADC: densify / prune)
"""

from __future__ import annotations

import json
import signal
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from .config import TrainConfig, load_config, save_config, to_jsonable
from .data import Scene, View, load_scene
from .errors import MCSplatError
from .events import (CheckpointWritten, Control, EvalDone, KernelsCompiling, Listener, RefineDone, RunFinished,
                     RunStarted, StepDone)
from .gaussians import GaussianModel
from .io.atomic import atomic_write, atomic_write_text, remove_stale_temporaries
from .io.checkpoint import load_checkpoint, save_checkpoint
from .io.ply import write_ply
from .losses import photometric_loss
from .metrics import lpips_model, psnr, ssim_metric
from .optim import make_optimizers, means_lr_at, set_means_lr
from .render import render, set_cpu_threads
from .render.compile import compile_kernels, modules_to_compile
from .strategy.adc import ADCStrategy
from .strategy.mcmc import MCMCStrategy
from .subscribers import Checkpointer, ConsoleLog, LogWriter, ProgressBar

CHECKPOINT = "checkpoint.pt"
DEAD_OPACITY = 0.005  # Gaussians at or below it are dead (SPEC 5) and left out of the exported .ply
RUN_MARKERS = ("config.json", CHECKPOINT, "metrics.json", "point_cloud.ply")


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise MCSplatError("--device cuda: no CUDA device is available here; use --device cpu (or auto)")
    return torch.device(name)


def background_of(config: TrainConfig, scene: Scene) -> tuple[float, float, float]:
    if config.background == "auto":
        return scene.background
    return (1.0, 1.0, 1.0) if config.background == "white" else (0.0, 0.0, 0.0)


PREFETCH_VIEWS = 2  # images decoded in the background ahead of their step (a no-op when all are in memory)


class ViewSampler:
    """Training views in random order, each once per pass (as 3DGS pops cameras from a shuffled copy)."""

    def __init__(self, count: int, seed: int):
        self.count = count
        self.generator = torch.Generator().manual_seed(seed)
        self.order: list[int] = []

    def next(self) -> int:
        if not self.order:
            self.order = torch.randperm(self.count, generator=self.generator).tolist()
        return self.order.pop()

    def upcoming(self, count: int) -> list[int]:
        """The next `count` indices `next()` will return within this pass (fewer near its end), for prefetching."""
        return self.order[-1:-count - 1:-1]

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "order": list(self.order)}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.order = list(state["order"])


def make_strategy(config: TrainConfig, scene_radius: float, generator: torch.Generator):
    if config.strategy == "mcmc":
        return MCMCStrategy(config.mcmc, scene_radius, generator)
    return ADCStrategy(config.adc, scene_radius, generator)


def initial_model(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator
                  ) -> tuple[GaussianModel, str]:
    m = config.model
    use_sfm = m.init == "sfm" or (m.init == "auto" and scene.points is not None and scene.kind != "blender")
    if use_sfm:
        if scene.points is None:
            raise MCSplatError(f"--model.init sfm: {scene.root} has no SfM points; use --model.init random")
        model = GaussianModel.from_points(scene.points, scene.point_colors, init_scale=m.init_scale,
                                          init_opacity=m.init_opacity, sh_degree=m.sh_degree, device=device)
        return model, f"SfM ({model.num_gaussians:,} points)"
    model = GaussianModel.random_init(scene.radius, blender=scene.kind == "blender", num_points=m.num_init_points,
                                      extent=m.init_extent, init_scale=m.init_scale, init_opacity=m.init_opacity,
                                      sh_degree=m.sh_degree, generator=generator, device=device)
    return model, f"random ({model.num_gaussians:,} points)"


@dataclass
class Evaluation:
    psnr: float
    ssim: float
    lpips: float | None
    lpips_net: str
    views: int
    per_view_psnr: dict[str, float] = field(default_factory=dict)  # view name -> PSNR


@torch.no_grad()
def evaluate(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
             lpips_net: str | None = None, render_dir: Path | None = None, progress: bool = False) -> Evaluation:
    """Mean PSNR / SSIM / LPIPS over `views`; optionally writes each render as PNG into `render_dir`."""
    if not views:
        raise MCSplatError("no test views to evaluate: the scene has no test split (check --test-every)")
    lp = lpips_model(lpips_net, device=device) if lpips_net else None
    scores = {"psnr": [], "ssim": [], "lpips": []}
    for view in tqdm(views, desc="evaluating", disable=not progress, leave=False):
        target = view.image_float(device)
        image = render(model, view.camera.to(device), background, sh_degree).rgb.clamp(0, 1)
        scores["psnr"].append(psnr(image, target))
        scores["ssim"].append(ssim_metric(image, target))
        if lp is not None:
            scores["lpips"].append(float(lp(image, target)))
        if render_dir is not None:
            save_png(render_dir / f"{Path(view.name).stem}.png", image)
    return Evaluation(psnr=float(np.mean(scores["psnr"])), ssim=float(np.mean(scores["ssim"])),
                      lpips=float(np.mean(scores["lpips"])) if scores["lpips"] else None,
                      lpips_net=lpips_net or "", views=len(views),
                      per_view_psnr={view.name: round(value, 3) for view, value in zip(views, scores["psnr"])})


def save_png(path: Path, image: torch.Tensor) -> None:
    pixels = (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    atomic_write(path, lambda tmp: Image.fromarray(pixels).save(tmp, format="PNG"))


def export_ply(model: GaussianModel, path: Path) -> int:
    """The standard 3DGS .ply without dead Gaussians; returns how many were written."""
    return write_ply(path, dict(model.params.items()), keep=model.opacities.detach() > DEAD_OPACITY)


class _CtrlC:
    """Ctrl-C asks the run to stop at the end of the current step (a second Ctrl-C stops at once)."""

    def __init__(self, control: Control) -> None:
        self.control = control
        self._previous = None

    def __enter__(self):
        def handler(signum, frame):
            if self.control.stop_requested:
                raise KeyboardInterrupt
            self.control.stop()
        try:
            self._previous = signal.signal(signal.SIGINT, handler)
        except ValueError:  # not the main thread: leave Ctrl-C alone
            self._previous = None
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _prepare_run_dir(config: TrainConfig) -> Path:
    run_dir = config.run_dir
    if run_dir.exists() and not run_dir.is_dir():
        raise MCSplatError(f"--out {run_dir}: exists and is not a directory")
    holds_run = run_dir.is_dir() and any((run_dir / m).exists() for m in RUN_MARKERS)
    if config.resume:
        if not (run_dir / CHECKPOINT).is_file():
            raise MCSplatError(f"--resume: {run_dir} has no {CHECKPOINT} to continue from")
        # A run killed while writing its checkpoint leaves the half-written temporary beside it.
        remove_stale_temporaries(run_dir / CHECKPOINT)
    elif holds_run and not config.overwrite:
        raise MCSplatError(f"{run_dir} already holds a run; pass --resume to continue it, --overwrite to replace its "
                           f"files, or --out to choose another directory")
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


# Options that only affect how this process runs: on --resume they come from the command line, the rest from
# the run's saved configuration (steps included: the learning-rate schedule depends on it).
PROCESS_OPTIONS = ("eval_every", "save_every", "quiet", "threads", "device", "viewer", "port", "host")


@dataclass
class StepResult:
    loss: float
    train_psnr: float
    info: dict[str, Any]  # what the strategy did after the optimizer step


def train_step(step: int, model: GaussianModel, optimizers: dict, strategy, view: View, *, config: TrainConfig,
               scene_radius: float, background, device: torch.device) -> StepResult:
    """One optimisation step on one training view (the module docstring lists its parts, in order)."""
    set_means_lr(optimizers, means_lr_at(step, config.steps, config.optim, scene_radius))
    sh_degree = sh_degree_at(config, step)
    target = view.image_float(device)
    camera = view.camera.to(device)
    result = render(model, camera, background, sh_degree)
    loss = photometric_loss(result.rgb, target, config.ssim_weight) + strategy.regularization(model)
    if not torch.isfinite(loss):
        raise MCSplatError(f"step {step}: the loss became {loss.item()}; lower the learning rates or check "
                           f"the input images (the last checkpoint is kept)")
    loss.backward()
    strategy.step_post_backward(step, model, result, camera.width, camera.height)
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    # The noise uses the position learning rate after this step's decay, as gsplat does (SPEC 13).
    info = strategy.step_post_optimizer(step, model, optimizers,
                                        means_lr_at(step + 1, config.steps, config.optim, scene_radius))
    return StepResult(loss=loss.item(), train_psnr=psnr(result.rgb.detach(), target), info=info)


def sh_degree_at(config: TrainConfig, step: int) -> int:
    return min(step // config.sh_increase_every, config.model.sh_degree)


class TrainingRun:
    """A training job: set up (or resumed) from its configuration, then `run(subscribers)` steps it to the end,
    emitting the events of events.py. `control` pauses or stops it from another thread."""

    def __init__(self, config: TrainConfig, control: Control | None = None):
        self.run_dir = _prepare_run_dir(config)
        if config.resume:
            saved = load_config(self.run_dir)
            for key in PROCESS_OPTIONS:
                setattr(saved, key, getattr(config, key))
            saved.resume, config = True, saved
        self.config = config
        self.control = control or Control()
        self.device = resolve_device(config.device)
        if config.threads is not None:
            torch.set_num_threads(config.threads)
        set_cpu_threads(config.threads)
        self.scene = load_scene(config.data, downscale=config.downscale, background=config.background
                                if config.background != "auto" else None, test_every=config.test_every)
        self.background = background_of(config, self.scene)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator(device=self.device).manual_seed(config.seed)
        self.sampler = ViewSampler(len(self.scene.train), config.seed)
        self.step, self.train_seconds = 0, 0.0
        radius = self.scene.radius
        if config.resume:
            state = load_checkpoint(self.run_dir / CHECKPOINT)
            self.model = GaussianModel.from_state_dict(state["model"]).to(self.device)
            self.optimizers = make_optimizers(self.model, config.optim, radius)
            for name, opt in self.optimizers.items():
                opt.load_state_dict(state["optimizers"][name])
            self.strategy = make_strategy(config, radius, self.generator)
            self.strategy.load_state_dict(state["strategy"])
            self.generator.set_state(state["generator"])
            self.sampler.load_state_dict(state["sampler"])
            self.step, self.train_seconds = state["step"], state["train_seconds"]
            self.init_note = f"resumed at step {self.step:,}"
        else:
            self.model, self.init_note = initial_model(config, self.scene, self.device, self.generator)
            self.optimizers = make_optimizers(self.model, config.optim, radius)
            self.strategy = make_strategy(config, radius, self.generator)
            save_config(config, self.run_dir / "config.json")
        self._emit: Listener = lambda event: None

    def save_checkpoint(self) -> None:
        path = self.run_dir / CHECKPOINT
        save_checkpoint(path, {
            "step": self.step, "train_seconds": self.train_seconds, "model": self.model.state_dict(),
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "strategy": self.strategy.state_dict(), "generator": self.generator.get_state(),
            "sampler": self.sampler.state_dict(), "config": to_jsonable(self.config)})
        self._emit(CheckpointWritten(step=self.step, path=path))

    def run(self, subscribers: Sequence[Listener]) -> dict[str, Any]:
        """Train to config.steps; returns the final metrics (also written to metrics.json)."""
        def emit(event) -> None:
            for subscriber in subscribers:
                subscriber(event)

        self._emit = emit
        try:
            emit(RunStarted(run=self, start_step=self.step, init_note=self.init_note))
            self._compile_kernels(emit)
            with _CtrlC(self.control):
                self._steps(emit)
            return self._finish(emit)
        finally:
            self._emit = lambda event: None
            _close_all(subscribers)

    def _compile_kernels(self, emit: Listener) -> None:
        """Compile (first run on a machine) or load the kernels before the first step, saying so when it compiles."""
        pending = modules_to_compile(self.device)
        if pending:
            emit(KernelsCompiling(modules=pending))
        compile_kernels(self.device)

    def _steps(self, emit: Listener) -> None:
        config, control = self.config, self.control
        while self.step < config.steps:
            control.wait_while_paused()
            with control.lock:
                tick = time.perf_counter()
                view = self.scene.train[self.sampler.next()]
                for index in self.sampler.upcoming(PREFETCH_VIEWS):  # decode ahead when images are not all in RAM
                    self.scene.train[index].prefetch()
                done = train_step(self.step, self.model, self.optimizers, self.strategy, view, config=config,
                                  scene_radius=self.scene.radius, background=self.background, device=self.device)
                counts = {k: int(v) for k, v in done.info.items() if k != "num_gaussians"}
                if any(counts.values()):
                    emit(RefineDone(step=self.step, counts=counts, num_gaussians=self.model.num_gaussians))
                self.step += 1
                self.train_seconds += time.perf_counter() - tick
                step = self.step
                if config.eval_every and step % config.eval_every == 0 and step < config.steps:
                    result = evaluate(self.model, self.scene.test, self.background, sh_degree_at(config, step - 1),
                                      self.device)
                    emit(EvalDone(step=step, psnr=result.psnr, ssim=result.ssim,
                                  num_gaussians=self.model.num_gaussians))
            emit(StepDone(step=step, total_steps=config.steps, loss=done.loss, train_psnr=done.train_psnr,
                          num_gaussians=self.model.num_gaussians, sh_degree=sh_degree_at(config, step - 1),
                          train_seconds=self.train_seconds, counts=counts))
            if control.stop_requested:
                self.save_checkpoint()
                raise MCSplatError(f"stopped at step {step:,}; the checkpoint is saved: continue with "
                                   f"`mcsplat train {config.data} --out {self.run_dir} --resume`")

    def _finish(self, emit: Listener) -> dict[str, Any]:
        config, run_dir = self.config, self.run_dir
        self.save_checkpoint()
        final_degree = final_sh_degree(config, self.step)
        evaluation = evaluate(self.model, self.scene.test, self.background, final_degree, self.device,
                              lpips_net=config.lpips_net,
                              render_dir=run_dir / "renders" / "test" if config.save_renders else None,
                              progress=not config.quiet)
        exported = export_ply(self.model, run_dir / "point_cloud.ply")
        metrics = {"psnr": evaluation.psnr, "ssim": evaluation.ssim, "lpips": evaluation.lpips,
                   "lpips_net": config.lpips_net, "num_gaussians": self.model.num_gaussians,
                   "exported_gaussians": exported, "steps": self.step, "train_seconds": round(self.train_seconds, 2),
                   "device": str(self.device), "strategy": config.strategy, "test_views": evaluation.views,
                   "sh_degree": final_degree, "per_view_psnr": evaluation.per_view_psnr}
        atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        emit(RunFinished(run=self, metrics=metrics, evaluation=evaluation))
        return metrics


def _close_all(subscribers: Sequence[Listener]) -> None:
    """Close every subscriber, even when one of them fails to (a viewer left open keeps its port and threads)."""
    for subscriber in subscribers:
        close = getattr(subscriber, "close", None)
        if close is None:
            continue
        try:
            close()
        except Exception as error:
            warnings.warn(f"{type(subscriber).__name__} did not close cleanly: {error}", RuntimeWarning, stacklevel=2)


def standard_subscribers(config: TrainConfig, run_dir: Path) -> list[Listener]:
    """The consumers every run has (progress bar, console lines, log.jsonl, periodic checkpoints, the report) and
    the live viewer when asked for."""
    from .report import ReportWriter  # matplotlib: loaded only when training

    subscribers = [ProgressBar(config.quiet), ConsoleLog(config.quiet), LogWriter(run_dir / "log.jsonl"),
                   Checkpointer(config.save_every), ReportWriter(config.quiet)]
    if config.viewer:
        from .viewer import TrainingViewer

        subscribers.append(TrainingViewer(host=config.host, port=config.port, quiet=config.quiet))
    return subscribers


def train(config: TrainConfig, subscribers: Sequence[Listener] = (), control: Control | None = None
          ) -> dict[str, Any]:
    """Run the whole job with the standard consumers plus `subscribers`; returns the final metrics."""
    if config.viewer:
        from .viewer import require_viser

        require_viser()  # before the run directory is made: a missing extra must not leave a half-started run
    run = TrainingRun(config, control)
    return run.run(standard_subscribers(run.config, run.run_dir) + list(subscribers))


def load_trained(run_dir: Path, device: torch.device) -> tuple[TrainConfig, GaussianModel, int]:
    """(config, model, step) of a finished or interrupted run, from its checkpoint."""
    config = load_config(run_dir)
    state = load_checkpoint(Path(run_dir) / CHECKPOINT)
    return config, GaussianModel.from_state_dict(state["model"]).to(device), int(state["step"])


def final_sh_degree(config: TrainConfig, step: int) -> int:
    return min(max(step - 1, 0) // config.sh_increase_every, config.model.sh_degree)
