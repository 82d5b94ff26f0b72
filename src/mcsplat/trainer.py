"""The training loop: schedules, progress, periodic evaluation, checkpoints and the run directory's outputs.

One step (SPEC 2, in gsplat's order, see strategy/mcmc.py for how the official code differs):
    render a training view -> loss = 0.8 L1 + 0.2 D-SSIM + strategy regularizers -> backward
    -> strategy.step_post_backward (ADC gradient statistics) -> Adam step for every parameter
    -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD noise; ADC: densify / prune)
"""

from __future__ import annotations

import json
import math
import signal
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from . import __version__
from .config import TrainConfig, load_config, save_config, to_jsonable
from .data import Scene, View, load_scene
from .data.scene import OBJECT_CENTRIC_KINDS
from .distributed import ProcessGroup, SingleProcess, join, scaled_for_processes, threads_per_process
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
from .visibility import count_invisible, seen_in

CHECKPOINT = "checkpoint.pt"
DEAD_OPACITY = 0.005  # Gaussians at or below it are dead (SPEC 5) and left out of the exported .ply
RUN_MARKERS = ("config.json", CHECKPOINT, "metrics.json", "point_cloud.ply")
Team = SingleProcess | ProcessGroup  # the processes training one model (one, or torchrun's)


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

    def take(self, count: int) -> list[int]:
        """The next `count` indices (one per process when several train together: each takes its own)."""
        return [self.next() for _ in range(count)]

    def upcoming(self, count: int) -> list[int]:
        """The next `count` indices `next()` will return within this pass (fewer near its end), for prefetching."""
        return self.order[-1:-count - 1:-1]

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "order": list(self.order)}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.order = list(state["order"])


def make_strategy(config: TrainConfig, scene_radius: float, generator: torch.Generator,
                  image_pixels: int | None = None):
    """image_pixels (a training image's, the median over them): the ceiling of MCMC's automatic cap."""
    if config.strategy == "mcmc":
        return MCMCStrategy(config.mcmc, scene_radius, generator, image_pixels)
    return ADCStrategy(config.adc, scene_radius, generator)


def training_image_pixels(scene: Scene) -> int:
    """The median pixel count of the scene's training images."""
    pixels = sorted(v.camera.width * v.camera.height for v in scene.train)
    return pixels[len(pixels) // 2] if pixels else 0


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
    model = GaussianModel.random_init(scene.radius, blender=scene.kind in OBJECT_CENTRIC_KINDS,
                                      num_points=m.num_init_points,
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


@dataclass
class ViewScore:
    name: str
    psnr: float
    ssim: float
    lpips: float | None


@torch.no_grad()
def score_views(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
                lpips_net: str | None = None, on_image=None, progress: bool = False) -> list[ViewScore]:
    """PSNR / SSIM / LPIPS of each view's render; `on_image(view, image)` sees each render (to save it)."""
    lp = lpips_model(lpips_net, device=device) if lpips_net else None
    scores = []
    for view in tqdm(views, desc="evaluating", disable=not progress, leave=False):
        target = view.image_float(device)
        image = render(model, view.camera.to(device), background, sh_degree).rgb.clamp(0, 1)
        scores.append(ViewScore(view.name, psnr(image, target), ssim_metric(image, target),
                                float(lp(image, target)) if lp is not None else None))
        if on_image is not None:
            on_image(view, image)
    return scores


def summarize(scores: list[ViewScore], lpips_net: str | None) -> Evaluation:
    """The means over the views (in the order given)."""
    lpips_values = [s.lpips for s in scores if s.lpips is not None]
    return Evaluation(psnr=float(np.mean([s.psnr for s in scores])), ssim=float(np.mean([s.ssim for s in scores])),
                      lpips=float(np.mean(lpips_values)) if lpips_values else None, lpips_net=lpips_net or "",
                      views=len(scores), per_view_psnr={s.name: round(s.psnr, 3) for s in scores})


def evaluate(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
             lpips_net: str | None = None, render_dir: Path | None = None, progress: bool = False) -> Evaluation:
    """Mean PSNR / SSIM / LPIPS over `views`; optionally writes each render as PNG into `render_dir`."""
    _require_test_views(views)
    save = (lambda view, image: save_png(render_dir / f"{Path(view.name).stem}.png", image)) if render_dir else None
    return summarize(score_views(model, views, background, sh_degree, device, lpips_net, save, progress), lpips_net)


def _require_test_views(views: list[View]) -> None:
    if not views:
        raise MCSplatError("no test views to evaluate: the scene has no test split (check --test-every)")


def save_png(path: Path, image: torch.Tensor) -> None:
    _save_pixels(path, _png_pixels(image))


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
PROCESS_OPTIONS = ("eval_every", "save_every", "quiet", "threads", "device", "viewer", "port", "host", "dist_timeout")


@dataclass
class StepResult:
    loss: float
    train_psnr: float
    info: dict[str, Any]  # what the strategy did after the optimizer step


Reduce = Callable[[GaussianModel, list[float]], list[float]]


def _alone(model: GaussianModel, values: list[float]) -> list[float]:
    return values


def train_step(step: int, model: GaussianModel, optimizers: dict, strategy, view: View, *, config: TrainConfig,
               scene_radius: float, background, device: torch.device, reduce: Reduce = _alone) -> StepResult:
    """One optimisation step on one training view (the module docstring lists its parts, in order).

    `reduce(model, [loss, psnr])` runs between the backward and the Adam step: with several processes it averages
    the gradients (and the two values) over them (distributed/team.py)."""
    set_means_lr(optimizers, means_lr_at(step, config.steps, config.optim, scene_radius))
    sh_degree = sh_degree_at(config, step)
    target = view.image_float(device)
    camera = view.camera.to(device)
    result = render(model, camera, background, sh_degree)
    loss = photometric_loss(result.rgb, target, config.ssim_weight) + strategy.regularization(model)
    loss.backward()
    strategy.step_post_backward(step, model, result, camera.width, camera.height)
    loss_value, train_psnr = reduce(model, [loss.item(), psnr(result.rgb.detach(), target)])
    if not math.isfinite(loss_value):  # checked after the reduce, so that every process stops at the same step
        raise MCSplatError(f"step {step}: the loss became {loss_value}; lower the learning rates or check "
                           f"the input images (the last checkpoint is kept)")
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    # The noise uses the position learning rate after this step's decay, as gsplat does (SPEC 13).
    info = strategy.step_post_optimizer(step, model, optimizers,
                                        means_lr_at(step + 1, config.steps, config.optim, scene_radius))
    return StepResult(loss=loss_value, train_psnr=train_psnr, info=info)


def sh_degree_at(config: TrainConfig, step: int) -> int:
    return min(step // config.sh_increase_every, config.model.sh_degree)


class TrainingRun:
    """A training job: set up (or resumed) from its configuration, then `run(subscribers)` steps it to the end,
    emitting the events of events.py. `control` pauses or stops it from another thread.

    With several processes (`team`, see mcsplat.distributed) every process runs this same loop on its own views;
    rank 0 alone reads and writes the run directory and has subscribers."""

    def __init__(self, config: TrainConfig, control: Control | None = None, team: Team | None = None):
        self.team = team = team or SingleProcess()
        team.check_same_setup(_setup_of(config))
        local = config
        config = team.on_main(lambda: _prepare_run(local))
        # This process's own options. The data path is its own too (it may differ between machines; the scenes are
        # compared below), except that a resumed run in one process trains on the data it started with.
        for key in PROCESS_OPTIONS + (() if config.resume and team.is_main else ("data",)):
            setattr(config, key, getattr(local, key))
        if config.resume:
            _check_resumable(config, team.world_size)
        else:
            config = scaled_for_processes(config, team.world_size)
        self.config = config
        self.run_dir = config.run_dir
        self.control = control or Control()
        self.device = team.device(resolve_device(config.device))
        threads = config.threads if config.threads is not None or team.world_size == 1 else threads_per_process()
        if threads is not None:
            torch.set_num_threads(threads)
        set_cpu_threads(threads)
        self.scene = load_scene(config.data, downscale=config.downscale, background=config.background
                                if config.background != "auto" else None, test_every=config.test_every)
        team.check_same_setup(_scene_summary(self.scene))
        self.background = background_of(config, self.scene)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator(device=self.device).manual_seed(config.seed)
        self.sampler = ViewSampler(len(self.scene.train), config.seed)
        self.step, self.train_seconds = 0, 0.0
        radius = self.scene.radius
        if config.resume:
            state = team.on_main(lambda: load_checkpoint(self.run_dir / CHECKPOINT))
            self.model = GaussianModel.from_state_dict(state["model"]).to(self.device)
            self.optimizers = make_optimizers(self.model, config.optim, radius)
            for name, opt in self.optimizers.items():
                opt.load_state_dict(state["optimizers"][name])
            self.strategy = make_strategy(config, radius, self.generator, training_image_pixels(self.scene))
            self.strategy.load_state_dict((state.get("strategy_per_process") or [state["strategy"]])[team.rank])
            self.generator.set_state(state["generator"])
            self.sampler.load_state_dict(state["sampler"])
            self.step, self.train_seconds = state["step"], state["train_seconds"]
            self.init_note = f"resumed at step {self.step:,}"
        else:
            self.model, self.init_note = initial_model(config, self.scene, self.device, self.generator)
            team.share_parameters(self.model)
            self.optimizers = make_optimizers(self.model, config.optim, radius)
            self.strategy = make_strategy(config, radius, self.generator, training_image_pixels(self.scene))
            if team.is_main:
                save_config(config, self.run_dir / "config.json")
        self.strategy.collective = team.collective
        self._stop_vote = False  # several processes: whether any of them asked to stop, agreed with the gradients
        self._emit: Listener = lambda event: None

    def save_checkpoint(self) -> None:
        """Rank 0 writes the checkpoint; every process calls this at the same steps, for the strategy's state
        differs between them (ADC's statistics of each process's own views) and rank 0 keeps them all."""
        strategies = self.team.gather_on_main(self.strategy.state_dict())
        if not self.team.is_main:
            return
        path = self.run_dir / CHECKPOINT
        save_checkpoint(path, {
            "step": self.step, "train_seconds": self.train_seconds, "model": self.model.state_dict(),
            "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
            "strategy": strategies[0], "strategy_per_process": strategies if len(strategies) > 1 else None,
            "generator": self.generator.get_state(), "sampler": self.sampler.state_dict(),
            "config": to_jsonable(self.config)})
        self._emit(CheckpointWritten(step=self.step, path=path))

    def run(self, subscribers: Sequence[Listener]) -> dict[str, Any]:
        """Train to config.steps; returns the final metrics (also written to metrics.json by rank 0)."""
        def emit(event) -> None:
            for subscriber in subscribers:
                subscriber(event)

        self._emit = emit
        try:
            emit(RunStarted(run=self, start_step=self.step, init_note=self.init_note))
            self.team.first_on_each_machine(lambda: self._compile_kernels(emit))
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

    def _reduce(self, model: GaussianModel, values: list[float]) -> list[float]:
        """The step's reduce (train_step): the stop requests of all processes travel with the gradients."""
        *averaged, stop = self.team.reduce_step(model, values + [float(self.control.stop_requested)])
        self._stop_vote = stop > 0
        return averaged

    def _stop_now(self) -> bool:
        # Alone, a stop asked for during this step's events counts at once; together, only what every process
        # agreed on in the step's all-reduce (or one would stop while the others wait for it).
        return self.control.stop_requested if self.team.world_size == 1 else self._stop_vote

    def _steps(self, emit: Listener) -> None:
        config, control, team = self.config, self.control, self.team
        n = team.world_size
        while self.step < config.steps:
            control.wait_while_paused()
            with control.lock:
                tick = time.perf_counter()
                view = self.scene.train[team.pick(self.sampler.take(n))]
                for index in self.sampler.upcoming(PREFETCH_VIEWS * n)[team.rank::n]:  # decode ahead when images
                    self.scene.train[index].prefetch()                                  # are not all in memory
                done = train_step(self.step, self.model, self.optimizers, self.strategy, view, config=config,
                                  scene_radius=self.scene.radius, background=self.background, device=self.device,
                                  reduce=self._reduce)
                counts = {k: int(v) for k, v in done.info.items() if k != "num_gaussians"}
                if any(counts.values()):
                    emit(RefineDone(step=self.step, counts=counts, num_gaussians=self.model.num_gaussians))
                self.step += 1
                self.train_seconds += time.perf_counter() - tick
                step = self.step
                team.check_identical(self.model, step)
                if config.eval_every and step % config.eval_every == 0 and step < config.steps:
                    result = self._evaluate(sh_degree_at(config, step - 1))
                    emit(EvalDone(step=step, psnr=result.psnr, ssim=result.ssim,
                                  num_gaussians=self.model.num_gaussians))
            emit(StepDone(step=step, total_steps=config.steps, loss=done.loss, train_psnr=done.train_psnr,
                          num_gaussians=self.model.num_gaussians, sh_degree=sh_degree_at(config, step - 1),
                          train_seconds=self.train_seconds, counts=counts))
            if self._stop_now():
                self.save_checkpoint()
                raise MCSplatError(f"stopped at step {step:,}; the checkpoint is saved: continue with "
                                   f"`mcsplat train {config.data} --out {self.run_dir} --resume`")

    def _evaluate(self, sh_degree: int, lpips_net: str | None = None, render_dir: Path | None = None,
                  progress: bool = False) -> Evaluation:
        """The test views' scores; with several processes each scores every N-th view and rank 0 gathers them
        (and writes the renders)."""
        views, team = self.scene.test, self.team
        _require_test_views(views)
        mine = list(range(team.rank, len(views), team.world_size))
        sent: list[tuple[str, np.ndarray]] = []  # renders rank 0 writes for the others

        def keep(view: View, image: torch.Tensor) -> None:
            if team.is_main:
                save_png(render_dir / f"{Path(view.name).stem}.png", image)
            else:
                sent.append((view.name, _png_pixels(image)))

        scores = score_views(self.model, [views[i] for i in mine], self.background, sh_degree, self.device,
                             lpips_net, keep if render_dir is not None else None, progress and team.is_main)
        everyone = team.gather((mine, scores))
        by_index = {i: score for indices, part in everyone for i, score in zip(indices, part)}
        if render_dir is not None:
            for images in team.gather_on_main(sent)[1:]:
                for name, pixels in images:
                    _save_pixels(render_dir / f"{Path(name).stem}.png", pixels)
        return summarize([by_index[i] for i in range(len(views))], lpips_net)

    def _seen_in_training_views(self) -> torch.Tensor:
        """[N] bool: composited into a pixel of some training view (each process renders every N-th view)."""
        team = self.team
        seen = seen_in(self.model, self.scene.train[team.rank::team.world_size], self.background, self.device)
        seen = seen.to(torch.uint8)
        team.collective.max_(seen)
        return seen.bool()

    def _finish(self, emit: Listener) -> dict[str, Any]:
        config, run_dir = self.config, self.run_dir
        self.save_checkpoint()
        final_degree = final_sh_degree(config, self.step)
        evaluation = self._evaluate(final_degree, lpips_net=config.lpips_net,
                                    render_dir=run_dir / "renders" / "test" if config.save_renders else None,
                                    progress=not config.quiet)
        invisible = count_invisible(self.model, self._seen_in_training_views())
        exported = export_ply(self.model, run_dir / "point_cloud.ply") if self.team.is_main else \
            int((self.model.opacities.detach() > DEAD_OPACITY).sum())
        metrics = {"psnr": evaluation.psnr, "ssim": evaluation.ssim, "lpips": evaluation.lpips,
                   "lpips_net": config.lpips_net, "num_gaussians": self.model.num_gaussians,
                   "exported_gaussians": exported, "steps": self.step, "train_seconds": round(self.train_seconds, 2),
                   "device": str(self.device), "strategy": config.strategy, "test_views": evaluation.views,
                   "sh_degree": final_degree, "processes": self.team.world_size,
                   "invisible_gaussians": invisible.as_dict(),
                   # --cap-max auto: where growth stopped (None: the demand never fell, the ceiling decided)
                   **({"auto_cap": self.strategy.chosen_cap, "auto_cap_ceiling": self.strategy.ceiling}
                      if config.cap_max == "auto" else {}),
                   "per_view_psnr": evaluation.per_view_psnr}
        if self.team.is_main:
            atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
        emit(RunFinished(run=self, metrics=metrics, evaluation=evaluation))
        return metrics


def _prepare_run(config: TrainConfig) -> TrainConfig:
    """Rank 0's part of the set-up: the run directory, and on --resume the run's saved configuration (with this
    command line's process options)."""
    run_dir = _prepare_run_dir(config)
    if not config.resume:
        return config
    saved = load_config(run_dir)
    for key in PROCESS_OPTIONS:
        setattr(saved, key, getattr(config, key))
    saved.out, saved.resume = run_dir, True  # where the run is now (the folder may have been moved)
    return saved


def _check_resumable(config: TrainConfig, world_size: int) -> None:
    if config.world_size != world_size:
        raise MCSplatError(f"this run was trained with {config.world_size} process(es), its step schedules and "
                           f"learning rates scaled for {config.world_size} views per step; resume it with the same "
                           f"number of processes (torchrun --nproc-per-node ... x --nnodes ...)")


def _setup_of(config: TrainConfig) -> dict[str, Any]:
    """What every process of one run must agree on: the options (not the per-process ones, nor the data path, which
    may differ between machines, but those that decide when the processes talk) and the versions that compute the
    steps."""
    options = {key: value for key, value in to_jsonable(config).items()
               if key not in PROCESS_OPTIONS + ("data", "out")}
    return {**options, "eval_every": config.eval_every, "save_every": config.save_every, "device": config.device,
            "mcsplat": __version__, "torch": torch.__version__}


def _scene_summary(scene: Scene) -> dict[str, Any]:
    """Enough of the loaded scene to tell two copies of one scene from two scenes."""
    return {"scene views": [(v.name, v.camera.width, v.camera.height) for v in scene.train + scene.test],
            "scene radius": round(float(scene.radius), 6)}


def _png_pixels(image: torch.Tensor) -> np.ndarray:
    return (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def _save_pixels(path: Path, pixels: np.ndarray) -> None:
    atomic_write(path, lambda tmp: Image.fromarray(pixels).save(tmp, format="PNG"))


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
    team = join(config.device, config.dist_timeout)
    finished = False
    try:
        if config.viewer and team.world_size > 1:
            raise MCSplatError("--viewer does not work with several training processes yet (pausing one would "
                               "stall the others); watch the run's checkpoints with `mcsplat view RUN` instead")
        run = TrainingRun(config, control, team)
        # The other processes take part in each checkpoint (save_checkpoint), without writing anything.
        consumers = standard_subscribers(run.config, run.run_dir) + list(subscribers) if team.is_main else \
            [Checkpointer(run.config.save_every)]
        metrics = run.run(consumers)
        finished = True
        return metrics
    finally:
        team.close(finished)


def load_trained(run_dir: Path, device: torch.device) -> tuple[TrainConfig, GaussianModel, int]:
    """(config, model, step) of a finished or interrupted run, from its checkpoint."""
    config = load_config(run_dir)
    state = load_checkpoint(Path(run_dir) / CHECKPOINT)
    return config, GaussianModel.from_state_dict(state["model"]).to(device), int(state["step"])


def final_sh_degree(config: TrainConfig, step: int) -> int:
    return min(max(step - 1, 0) // config.sh_increase_every, config.model.sh_degree)
