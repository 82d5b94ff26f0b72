"""The training loop: one step (`train_step`) and the run that repeats it (`TrainingRun`), emitting events.py's events.

One step (docs/method.md, "One training step"; in gsplat's order, see strategy/mcmc.py for how the official code
differs):
    render a training view (from its corrected pose with --pose-opt; through its colour transform with
    --appearance) -> loss = 0.8 L1 + 0.2 D-SSIM (over
    the pixels a mask keeps) + strategy regularizers -> backward
    -> strategy.step_post_backward (ADC gradient statistics) -> Adam step for every parameter
    -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD noise; ADC: densify / prune)

Where the run's files go is run_dir.py's business, how its state starts and what a checkpoint holds state.py's,
scoring evaluation.py's; train.py puts a run together with its consumers.
"""

from __future__ import annotations

import dataclasses
import math
import signal
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import torch

from . import __version__, losses, render, run_dir
from .appearance import Compensation, training_kernels as appearance_kernels
from .pose_refinement import PoseRefinement
from .budget import BudgetPlanner
from .compute.compile import compile_kernels, modules_to_compile
from .compute.device import resolve_device
from .config import PROCESS_OPTIONS, TrainConfig, to_jsonable
from .data import Scene, View
from .distributed import SingleProcess, Team, command_for, scaled_for_processes, threads_per_process
from .errors import MCSplatError
from .evaluation import Evaluation, evaluate, seen_in_views
from .events import (CheckpointWritten, Control, EvalDone, KernelsCompiling, Listener, RefineDone, RunFinished,
                     RunStarted, StepDone)
from .gaussians import PARAM_KEYS, GaussianModel
from .io.lock import FolderLock
from .losses import masked_photometric_loss
from .metrics import psnr
from .optim import make_optimizers, means_lr_at, set_means_lr
from .render import RenderResult, set_cpu_threads
from .schedule import final_sh_degree, fitted_to_steps, planned_growth_rate, resolution_at, sh_degree_at
from .state import make_strategy, start, training_image_pixels
from .strategy.auto_cap import pixel_ceiling
from .strategy.base import RefineReport, changed
from .strategy.mcmc import prune_to_cap
from .strategy.noise import noise_lr_at
from .visibility import count_invisible

PREFETCH_VIEWS = 2  # images decoded in the background ahead of their step (a no-op when all are in memory)
CALIBRATION_SMALL, CALIBRATION_LARGE = 2000, 3  # --budget times models of 2,000 and of 3x the starting Gaussians


@dataclass
class StepResult:
    loss: float
    train_psnr: float
    refine: RefineReport  # what the strategy did after the optimizer step


Reduce = Callable[[GaussianModel, list[float]], list[float]]


def _alone(model: GaussianModel, values: list[float]) -> list[float]:
    return values


class StepPhases(Protocol):
    """Told where a step is: benchmarks/train_speed.py times the phases with it (the trainer passes none)."""

    def rendered(self, result: RenderResult) -> None:
        """After render(), before the loss."""
        ...

    def lap(self, phase: str) -> None:
        """The work since the previous mark was `phase`: other, render, loss, backward, strategy, reduce,
        optimizer."""
        ...


def train_step(step: int, model: GaussianModel, optimizers: dict, strategy, view: View, *, config: TrainConfig,
               scene_radius: float, background, device: torch.device, reduce: Reduce = _alone,
               phases: StepPhases | None = None, compensation: Compensation | None = None,
               poses: PoseRefinement | None = None, view_index: int = 0) -> StepResult:
    """One optimisation step on one training view (the module docstring lists its parts, in order).

    `reduce(model, [loss, psnr])` runs between the backward and the Adam step: with several processes it averages
    the gradients (and the two values) over them (distributed/team.py). With `compensation` (--appearance) the
    render goes through training view `view_index`'s colour transform before the loss; with `poses` (--pose-opt)
    the view is rendered from its corrected pose, and the correction takes a step with the scene."""
    lap = phases.lap if phases is not None else (lambda phase: None)
    set_means_lr(optimizers, means_lr_at(step, config.steps, config.optim, scene_radius))
    camera = view.camera_at(resolution_at(config, step)).to(device)  # coarse to fine, when configured
    if poses is not None:
        camera = poses.camera(view_index, camera)
    target = view.image_float(device, size=(camera.width, camera.height))
    keep = view.mask_float(device, size=(camera.width, camera.height))  # None unless the scene has masks
    lap("other")
    result = render.render(model, camera, background, sh_degree_at(config, step))
    lap("render")
    rgb = result.rgb if compensation is None else compensation.apply(view_index, result.rgb)
    loss = masked_photometric_loss(rgb, target, keep, config.ssim_weight) + strategy.regularization(model)
    if compensation is not None:
        loss = loss + compensation.regularization(view_index)
    lap("loss")
    if phases is not None:
        phases.rendered(result)
    loss.backward()
    lap("backward")
    strategy.step_post_backward(step, model, result, camera.width, camera.height)
    lap("strategy")
    loss_value, train_psnr = reduce(model, [loss.item(), psnr(rgb.detach(), target)])
    if not math.isfinite(loss_value):  # checked after the reduce, so that every process stops at the same step
        raise MCSplatError(f"step {step}: the loss became {loss_value}; lower the learning rates or check "
                           f"the input images (the last checkpoint is kept)")
    lap("reduce")
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    if compensation is not None:
        compensation.step(step, config.steps)
    if poses is not None:
        poses.step()
    lap("optimizer")
    # The noise uses the position learning rate after this step's decay, as gsplat does (docs/method.md), or the
    # schedule an ablation puts in its place (strategy/noise.py).
    refine = strategy.step_post_optimizer(step, model, optimizers,
                                          noise_lr_at(config.mcmc.noise_schedule, step + 1, config.steps,
                                                      config.optim, scene_radius))
    lap("strategy")
    return StepResult(loss=loss_value, train_psnr=train_psnr, refine=refine)


def step_kernels(device: torch.device, appearance: str = "none") -> list:
    """Every Warp kernel a training step launches on `device` (compiled before the first step)."""
    return render.training_kernels(device) + losses.training_kernels(device) + appearance_kernels(appearance)


class _CtrlC:
    """Ctrl-C, and SIGTERM (what `kill`, `timeout`, docker, SLURM and Kubernetes send), ask the run to stop at the
    end of the current step, which saves a checkpoint (a second signal stops at once). Once the last step's
    checkpoint is written (`stop_at_once`), a signal stops at once: --resume makes what the end of the run makes."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, control: Control) -> None:
        self.control = control
        self.at_once = False
        self._previous: dict = {}

    def stop_at_once(self) -> None:
        """From now on a signal raises KeyboardInterrupt where the run is; so does one that came before."""
        self.at_once = True
        if self.control.stop_requested:
            raise KeyboardInterrupt

    def __enter__(self):
        def handler(signum, frame):
            if self.at_once or self.control.stop_requested:
                raise KeyboardInterrupt
            self.control.stop()
        try:
            for number in self.SIGNALS:
                self._previous[number] = signal.signal(number, handler)
        except ValueError:  # not the main thread: leave the signals alone
            pass
        return self

    def __exit__(self, *exc) -> None:
        for number, previous in self._previous.items():
            if previous is not None:  # None: a handler set outside Python, which cannot be put back
                signal.signal(number, previous)
        self._previous = {}


class TrainingRun:
    """A training job: set up (or resumed) from its configuration, then `run(subscribers)` steps it to the end,
    emitting the events of events.py (it is their RunView). `control` pauses or stops it from another thread.

    With several processes (`team`, see mcsplat.distributed) every process runs this same loop on its own views;
    rank 0 alone reads and writes the run directory and has subscribers."""

    def __init__(self, config: TrainConfig, control: Control | None = None, team: Team | None = None,
                 lock: FolderLock | None = None):
        self.team = team = team or SingleProcess()
        if (config.appearance != "none" or config.pose_opt) and team.world_size > 1:
            raise MCSplatError("--appearance and --pose-opt do not work with several training processes yet (each "
                               "holds the corrections of its own views); train in one process, or leave them out")
        team.check_same_setup(_setup_of(config))
        local = config
        self.lock = lock or run_dir.train_lock(config)  # rank 0 takes it in prepare; run() releases it
        config = team.on_main(lambda: run_dir.prepare(local, self.lock, team.world_size))
        # This process's own options. The data path is its own too (it may differ between machines; the scenes are
        # compared below), except that a resumed run in one process trains on the data it started with.
        for key in PROCESS_OPTIONS + (() if config.resume and team.is_main else ("data",)):
            setattr(config, key, getattr(local, key))
        if config.resume:
            run_dir.check_resumable(config, team.world_size)
        else:  # a fixed number of steps gets its schedules fitted here; --budget fits them as it plans
            config = scaled_for_processes(config if config.budget else fitted_to_steps(config), team.world_size)
        self.config = config
        self.folder = run_dir.RunDir(config.run_dir)
        self.run_dir = self.folder.path
        self.control = control or Control()
        self.device = team.device(resolve_device(config.device))
        threads = config.threads if config.threads is not None or team.world_size == 1 else threads_per_process()
        if threads is not None:
            torch.set_num_threads(threads)
        set_cpu_threads(threads)
        self.scene: Scene = run_dir.scene_of(config)
        team.check_same_setup(_scene_summary(self.scene))
        self.background = run_dir.background_of(config, self.scene)
        if not self.scene.test and config.eval_every and team.is_main:
            warnings.warn(f"--eval-every {config.eval_every} is ignored: the scene has no test views to evaluate "
                          f"(--test-every {config.test_every})", stacklevel=2)
        checkpoint = team.on_main(lambda: self.folder.read_checkpoint_of(config)) if config.resume else None
        self.state, self.init_note = start(config, self.scene, self.device, team, checkpoint,
                                           progress=not config.quiet and team.is_main)
        self.planner = self._budget_planner()
        if not config.resume:
            self._plan_growth()
        if team.is_main:
            self.folder.begin(config, self.state.step)
        # Several processes: whether any of them asked to stop / for a checkpoint, agreed with the gradients.
        self._stop_vote = self._save_vote = False
        self._saved_at = -1  # the step of the last checkpoint written
        self._emit: Listener = lambda event: None

    @property
    def model(self) -> GaussianModel:
        return self.state.model

    @property
    def world_size(self) -> int:
        return self.team.world_size

    def _plan_growth(self) -> None:
        """With --cap-max, MCMC grows fast enough to reach that cap (or the automatic cap's ceiling) by growth_share
        of the run; the default cap (the paper's 1M) is a ceiling, not a target. Under --budget the planner sets the
        rate as it plans the cap."""
        if self.config.strategy == "mcmc" and self.config.cap_max is not None and self.planner is None:
            self.config.mcmc.grow_rate = planned_growth_rate(self.config, self.state.model.num_gaussians,
                                                             self.state.strategy.ceiling)

    def _budget_planner(self) -> BudgetPlanner | None:
        """--budget: the planner, bounded by --cap-max and the automatic cap's 3 Gaussians per pixel."""
        config = self.config
        if config.budget is None:
            return None
        if self.team.world_size > 1:
            raise MCSplatError("--budget does not work with several training processes yet (each would plan its own "
                               "steps); give --steps instead")
        cap = config.mcmc.cap_max if config.strategy == "mcmc" else (config.adc.cap_max or config.mcmc.cap_max)
        ceiling = pixel_ceiling(cap, training_image_pixels(self.scene), config.mcmc.gaussians_per_pixel)
        return BudgetPlanner(config, ceiling)

    def _start_budget(self) -> None:
        """Time a few steps, make the first plan, and cut an initialisation larger than it affords."""
        state = self.state
        self._calibrate()
        self.planner.start(state.step, state.wall_seconds, state.model.num_gaussians)
        if self.config.strategy == "mcmc" and state.step == 0:
            prune_to_cap(state.model, state.optimizers, self.config.mcmc.cap_max)

    def _calibrate(self) -> None:
        """Time steps of throwaway copies of the model, small and large, at full size and at the starting size, so
        that the first plan knows what pixels and Gaussians cost (not counted in the budget)."""
        config, state = self.config, self.state
        count = state.model.num_gaussians
        small = min(count, CALIBRATION_SMALL)
        views = self.scene.train[:2]
        for gaussians, scale in ((small, 1.0), (small, config.resolution_start), (count, 1.0),
                                 (CALIBRATION_LARGE * count, 1.0), (CALIBRATION_LARGE * count, config.resolution_start)):
            probe = dataclasses.replace(config, resolution_start=scale, resolution_full_at=1.0, steps=10**9)
            model = _resized(state.model, gaussians)
            optimizers = make_optimizers(model, config.optim, self.scene.radius)
            strategy = make_strategy(probe, self.scene.radius, torch.Generator(self.device).manual_seed(0))
            for i, view in enumerate(views):
                tick = time.perf_counter()
                train_step(0, model, optimizers, strategy, view, config=probe, scene_radius=self.scene.radius,
                           background=self.background, device=self.device)
                if i:  # the first is a warm-up
                    self.planner.calibrate(time.perf_counter() - tick, model.num_gaussians, scale)

    def save_checkpoint(self) -> None:
        """Rank 0 writes the checkpoint; every process calls this at the same steps, for the strategy's state
        differs between them (ADC's statistics of each process's own views) and rank 0 keeps them all."""
        self._saved_at = self.state.step
        strategies = self.team.gather_on_main(self.state.strategy.state_dict())
        if not self.team.is_main:
            return
        if self.planner is not None:  # --budget: config.json keeps the plan the checkpoint continues
            self.config.budget_plan = self.planner.record()
            self.folder.write_config(self.config)
        self.folder.write_checkpoint(self.state.checkpoint(self.config, strategies))
        self.control.checkpoint_done()
        self._emit(CheckpointWritten(step=self.state.step, path=self.folder.checkpoint_file))

    def run(self, subscribers: Sequence[Listener]) -> dict[str, Any]:
        """Train to config.steps; returns the final metrics (also written to metrics.json by rank 0)."""
        def emit(event) -> None:
            for subscriber in subscribers:
                subscriber(event)

        self._emit = emit
        try:
            emit(RunStarted(run=self, start_step=self.state.step, init_note=self.init_note))
            self.team.first_on_each_machine(lambda: self._compile_kernels(emit))
            if self.planner is not None:
                self._start_budget()
            with _CtrlC(self.control) as signals:
                self._steps(emit)
                return self._finish(emit, signals)
        finally:
            self._emit = lambda event: None
            _close_all(subscribers)
            self.lock.release()

    def _compile_kernels(self, emit: Listener) -> None:
        """Compile (first run on a machine) or load the kernels before the first step, saying so when it compiles."""
        kernels = step_kernels(self.device, self.config.appearance)
        pending = modules_to_compile(kernels, self.device)
        if pending:
            emit(KernelsCompiling(modules=pending))
        compile_kernels(kernels, self.device)

    def _reduce(self, model: GaussianModel, values: list[float]) -> list[float]:
        """The step's reduce (train_step): the stop requests of all processes travel with the gradients."""
        control = self.control
        *averaged, stop, save = self.team.reduce_step(
            model, values + [float(control.stop_requested), float(control.checkpoint_requested)])
        self._stop_vote, self._save_vote = stop > 0, save > 0
        return averaged

    def _stop_now(self) -> bool:
        # Alone, a stop asked for during this step's events counts at once; together, only what every process
        # agreed on in the step's all-reduce (or one would stop while the others wait for it).
        return self.control.stop_requested if self.team.world_size == 1 else self._stop_vote

    def _save_now(self) -> bool:
        """A checkpoint asked for through Control (by time, see subscribers.Checkpointer), agreed as a stop is."""
        if self._saved_at == self.state.step:  # the periodic checkpoint of this very step was written already
            return False
        return self.control.checkpoint_requested if self.team.world_size == 1 else self._save_vote

    def _done(self) -> bool:
        if self.planner is not None:
            return self.planner.finished(self.state.step, self.state.wall_seconds)
        return self.state.step >= self.config.steps

    def _steps(self, emit: Listener) -> None:
        config, control, team, state = self.config, self.control, self.team, self.state
        n = team.world_size
        while not self._done():
            control.wait_while_paused()
            started = time.perf_counter()
            with control.lock:
                tick = time.perf_counter()
                view_index = team.pick(state.sampler.take(n))
                view = self.scene.train[view_index]
                for index in state.sampler.upcoming(PREFETCH_VIEWS * n)[team.rank::n]:  # decode ahead when images
                    self.scene.train[index].prefetch()                                   # are not all in memory
                count, scale = state.model.num_gaussians, resolution_at(config, state.step)
                done = train_step(state.step, state.model, state.optimizers, state.strategy, view, config=config,
                                  scene_radius=self.scene.radius, background=self.background, device=self.device,
                                  reduce=self._reduce, compensation=state.compensation, poses=state.poses,
                                  view_index=view_index)
                if changed(done.refine):
                    emit(RefineDone(step=state.step, report=done.refine))
                state.step += 1
                seconds = time.perf_counter() - tick
                state.train_seconds += seconds
                step = state.step
                team.check_identical(state.model, step)
                if config.eval_every and self.scene.test and step % config.eval_every == 0 and step < config.steps:
                    result = self._evaluate(sh_degree_at(config, step - 1))
                    emit(EvalDone(step=step, psnr=result.psnr, ssim=result.ssim,
                                  num_gaussians=state.model.num_gaussians))
            state.wall_seconds += time.perf_counter() - started
            if self.planner is not None:  # before StepDone, so that it carries the plan's steps
                self._follow_budget(seconds, count, scale)
            emitted = time.perf_counter()
            emit(StepDone(step=step, total_steps=config.steps, loss=done.loss, train_psnr=done.train_psnr,
                          num_gaussians=state.model.num_gaussians, sh_degree=sh_degree_at(config, step - 1),
                          train_seconds=state.train_seconds, refine=done.refine, resolution=scale))
            state.wall_seconds += time.perf_counter() - emitted
            if self._stop_now():
                self.save_checkpoint()
                raise MCSplatError(f"stopped at step {step:,}; the checkpoint is saved: continue with "
                                   f"`{command_for(n)} train {config.data} --out {self.run_dir} --resume`")
            if self._save_now():
                self.save_checkpoint()

    def _follow_budget(self, step_seconds: float, count: int, scale: float) -> None:
        """--budget: measure the step, plan again when due (config.json keeps the plan)."""
        state, planner = self.state, self.planner
        planner.observe(step_seconds, count, scale)
        if planner.due(state.step, state.wall_seconds):
            planner.replan(state.step, state.wall_seconds, state.model.num_gaussians)
        if planner.finished(state.step, state.wall_seconds):  # the time is up: this step is the last one
            self.config.steps = state.step

    def _evaluate(self, sh_degree: int, lpips_net: str | None = None, save_renders: bool = False,
                  progress: bool = False) -> Evaluation:
        """The test views' scores, split between the processes (rank 0 writes the renders)."""
        render_file = (lambda name: self.folder.render_file("test", name)) if save_renders else None
        return evaluate(self.state.model, self.scene.test, self.background, sh_degree, self.device, lpips_net,
                        render_file, progress, team=self.team)

    def _finish(self, emit: Listener, signals: _CtrlC) -> dict[str, Any]:
        """The last checkpoint, then the final evaluation, point_cloud.ply, metrics.json and RunFinished (the
        report); a signal after that checkpoint stops the run with one line that says how to finish it."""
        if self.planner is not None:  # the run ends at the step it reached: what the last plan said, or fewer
            self.config.steps = self.state.step
        self.save_checkpoint()
        try:
            signals.stop_at_once()
            return self._final_results(emit)
        except KeyboardInterrupt:
            raise MCSplatError(f"stopped at step {self.state.step:,} while finishing the run (its final evaluation, "
                               f"{run_dir.SPLATS}, {run_dir.METRICS} and report); the checkpoint is saved: finish "
                               f"it with `{command_for(self.team.world_size)} train {self.config.data} --out "
                               f"{self.run_dir} --resume`") from None

    def _final_results(self, emit: Listener) -> dict[str, Any]:
        config, state, team = self.config, self.state, self.team
        final_degree = final_sh_degree(config, state.step)
        evaluation = None  # a scene without test views (--test-every 0) ends without test scores
        if self.scene.test:
            evaluation = self._evaluate(final_degree, lpips_net=config.lpips_net, save_renders=config.save_renders,
                                        progress=not config.quiet)
        seen = seen_in_views(state.model, self.scene.train, self.background, self.device, team)
        invisible = count_invisible(state.model, seen)
        exported = self.folder.export_splats(state.model) if team.is_main else int(run_dir.alive(state.model).sum())
        strategy = state.strategy
        scores = _scores(evaluation)
        metrics = {**{key: scores[key] for key in ("psnr", "ssim", "lpips")},
                   "lpips_net": config.lpips_net, "num_gaussians": state.model.num_gaussians,
                   "exported_gaussians": exported, "steps": state.step, "train_seconds": round(state.train_seconds, 2),
                   "device": str(self.device), "strategy": config.strategy, "test_views": scores["test_views"],
                   "sh_degree": final_degree, "processes": team.world_size,
                   "wall_seconds": round(state.wall_seconds, 2),
                   **({"budget_seconds": self.planner.budget} if self.planner is not None else {}),
                   "invisible_gaussians": invisible.as_dict(),
                   # --cap-max auto: where growth stopped (None: the demand never fell, the ceiling decided)
                   **({"auto_cap": strategy.chosen_cap, "auto_cap_ceiling": strategy.ceiling}
                      if config.cap_max == "auto" else {}),
                   **scores["masked"], **scores["compensated"],
                   **({"pose_corrections": state.poses.summary()} if state.poses is not None else {}),
                   "per_view_psnr": scores["per_view_psnr"]}
        if team.is_main:
            self.folder.write_metrics(metrics)
        emit(RunFinished(run=self, metrics=metrics, evaluation=evaluation))
        return metrics


def _scores(evaluation: Evaluation | None) -> dict[str, Any]:
    """What metrics.json records of the final evaluation: None scores and no views when there was none."""
    if evaluation is None:
        return {"psnr": None, "ssim": None, "lpips": None, "test_views": 0, "masked": {}, "compensated": {},
                "per_view_psnr": {}}
    return {"psnr": evaluation.psnr, "ssim": evaluation.ssim, "lpips": evaluation.lpips, "test_views": evaluation.views,
            "masked": evaluation.masked(), "compensated": evaluation.compensated(),
            "per_view_psnr": evaluation.per_view_psnr}


def _resized(model: GaussianModel, count: int) -> GaussianModel:
    """A detached model of `count` Gaussians: the first `count` of `model`, or copies of it side by side."""
    copies = -(-count // max(model.num_gaussians, 1))
    resized = GaussianModel(*(torch.cat([model.params[key].detach()] * copies)[:count] for key in PARAM_KEYS))
    resized.antialiased = model.antialiased
    return resized


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
