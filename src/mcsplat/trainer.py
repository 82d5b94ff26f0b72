"""The training loop: one step (`train_step`) and the run that repeats it (`TrainingRun`), emitting events.py's events.

One step (docs/method.md, "One training step"; in gsplat's order, see strategy/mcmc.py for how the official code
differs):
    render a training view (camera and render through the per-image modules, per_image.py: --pose-opt, --appearance)
    -> loss = the sum of the loss terms (loss_terms.py: 0.8 L1 + 0.2 D-SSIM over the pixels a mask keeps, strategy
    and module regularizers) -> backward -> strategy.step_post_backward (ADC gradient statistics) -> Adam steps
    -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD noise; ADC: densify / prune)

Where the run's files go is run_dir.py's business, how its state starts and what a checkpoint holds state.py's, what
the run decides (its steps, schedules and cap) its planner's (planning/), scoring evaluation.py's and metrics.json's
layout run_metrics.py's; train.py puts a run together with its consumers.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence

import torch

from . import losses, optim, render, run_dir, run_start
from .appearance import training_kernels as appearance_kernels
from .compute.compile import compile_kernels, modules_to_compile
from .config import TrainConfig
from .data import View
from .distributed import SingleProcess, Team, command_for
from .errors import MCSplatError
from .evaluation import Evaluation, evaluate, seen_in_views
from .events import (CheckpointWritten, Control, EvalDone, KernelsCompiling, Listener, RefineDone, RunFinished,
                     RunStarted, StepDone, close_all)
from .gaussians import GaussianModel
from .io.lock import FolderLock
from .loss_terms import LossTerm, StepContext, render_outputs, standard_terms, total_loss
from .metrics import psnr
from .optim import means_lr_at, set_means_lr
from .planning import Plan, run_record
from .per_image import PerImageModule
from .render import RenderResult
from .run_metrics import RunFacts, metrics
from .run_setup import set_up
from .state import feature_facts
from .stopping import AgreedRequests, StopSignals
from .strategy.base import RefineReport, asks_the_scene, changed
from .strategy.noise import noise_lr_at
from .visibility import count_invisible

PREFETCH_VIEWS = 2  # images decoded in the background ahead of their step (a no-op when all are in memory)


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
               plan: Plan, scene_radius: float, background, device: torch.device, reduce: Reduce = _alone,
               phases: StepPhases | None = None, modules: Sequence[PerImageModule] = (),
               loss_terms: Sequence[LossTerm] | None = None, view_index: int = 0) -> StepResult:
    """One optimisation step on one training view (the module docstring lists its parts, in order), as `plan` has
    it at this step (learning rates, resolution, SH degree; the strategy follows the plan's schedule).

    `reduce(model, [loss, psnr])` runs between the backward and the Adam step: with several processes it averages
    the gradients (and the two values) over them (distributed/team.py). Each of `modules` sees training view
    `view_index`'s camera and render, in order, and takes its own step after the scene's. The loss is the sum of
    `loss_terms` (by default loss_terms.standard_terms: photometric, the strategy's, each module's)."""
    lap = phases.lap if phases is not None else (lambda phase: None)
    set_means_lr(optimizers, means_lr_at(step, plan.steps, plan.optim, scene_radius))
    camera = view.camera_at(plan.resolution_at(step)).to(device)  # coarse to fine, when configured
    for module in modules:
        camera = module.camera(view_index, camera)
    target = view.image_float(device, size=(camera.width, camera.height))
    keep = view.mask_float(device, size=(camera.width, camera.height))  # None unless the scene has masks
    terms = loss_terms if loss_terms is not None else standard_terms(config.ssim_weight, strategy, modules)
    lap("other")
    result = render.render(model, camera, background, plan.sh_degree_at(step),
                           **render_outputs(terms, step, plan.steps))
    lap("render")
    rgb = result.rgb
    for module in modules:
        rgb = module.apply(view_index, rgb)
    loss = total_loss(terms, StepContext(step, view, view_index, camera, rgb, target, keep, model, result,
                                         plan.steps))
    lap("loss")
    if phases is not None:
        phases.rendered(result)
    loss.backward()
    lap("backward")
    strategy.step_post_backward(step, model, result, camera.width, camera.height)
    lap("strategy")
    loss_value, train_psnr = reduce(model, [loss.item(), psnr(rgb.detach(), target)])
    if not math.isfinite(loss_value):  # checked after the reduce, so that every process stops at the same step
        raise MCSplatError(f"step {step}: the loss became {loss_value}; lower the learning rates or the loss terms' "
                           f"weights (--surface-*, --appearance-*, --*depth*), or check the input images")
    lap("reduce")
    optim.step_optimizers(optimizers)  # and the gradients dropped
    for module in modules:
        module.step(step, plan)
    lap("optimizer")
    # The noise uses the position learning rate after this step's decay, as gsplat does (docs/method.md), or the
    # schedule an ablation puts in its place (strategy/noise.py).
    refine = strategy.step_post_optimizer(step, model, optimizers,
                                          noise_lr_at(config.mcmc.noise_schedule, step + 1, plan.steps, plan.optim,
                                                      scene_radius))
    lap("strategy")
    return StepResult(loss=loss_value, train_psnr=train_psnr, refine=refine)


def step_kernels(device: torch.device, appearance: str = "none") -> list:
    """Every Warp kernel a training step launches on `device` (compiled before the first step)."""
    return (render.training_kernels(device) + losses.training_kernels(device) + optim.training_kernels(device)
            + appearance_kernels(appearance))


class TrainingRun:
    """A training job: set up (or resumed) from its configuration, then `run(subscribers)` steps it to the end,
    emitting the events of events.py (it is their RunView). `control` pauses or stops it from another thread.

    With several processes (`team`, see mcsplat.distributed) every process runs this same loop on its own views;
    rank 0 alone reads and writes the run directory and has subscribers."""

    def __init__(self, config: TrainConfig, control: Control | None = None, team: Team | None = None,
                 lock: FolderLock | None = None):
        self.team = team = team or SingleProcess()
        self.lock = lock or run_start.train_lock(config)  # rank 0 takes it as the run is set up; run() releases it
        begun = set_up(config, team, self.lock)
        self.config, self.folder, self.device, self.scene = begun.config, begun.folder, begun.device, begun.scene
        self.background, self.state, self.init_note = begun.background, begun.state, begun.init_note
        self.planner, self.run_dir, self.control = begun.planner, begun.folder.path, control or Control()
        self.requests = AgreedRequests(self.control, team)  # stop / checkpoint, agreed between the processes
        self._written_plan = self.plan  # what config.json holds
        self._saved_at = -1  # the step of the last checkpoint written
        self._emit: Listener = lambda event: None

    @property
    def model(self) -> GaussianModel:
        return self.state.model

    @property
    def plan(self) -> Plan:
        return self.planner.plan

    @property
    def world_size(self) -> int:
        return self.team.world_size

    def save_checkpoint(self) -> None:
        """Rank 0 writes the checkpoint; every process calls this at the same steps, for the strategy's state
        differs between them (ADC's statistics of each process's own views) and rank 0 keeps them all."""
        self._saved_at = self.state.step
        strategies = self.team.gather_on_main(self.state.strategy.state_dict())
        if not self.team.is_main:
            return
        if self.plan != self._written_plan:  # --budget planned again: config.json keeps the plan it continues
            self.folder.write_config(self.config, self.plan)
            self._written_plan = self.plan
        self.folder.write_checkpoint(self.state.checkpoint(run_record(self.config, self.plan), strategies))
        self.control.checkpoint_done()
        self._emit(CheckpointWritten(step=self.state.step, path=self.folder.checkpoint_file))

    def run(self, subscribers: Sequence[Listener]) -> dict[str, Any]:
        """Train to the plan's end; returns the final metrics (also written to metrics.json by rank 0)."""
        def emit(event) -> None:
            for subscriber in subscribers:
                subscriber(event)

        self._emit = emit
        try:
            emit(RunStarted(run=self, start_step=self.state.step, init_note=self.init_note))
            self.team.first_on_each_machine(lambda: self._compile_kernels(emit))
            self.planner.begin(self.state, self.scene, self.background, self.device, train_step)
            with StopSignals(self.control) as signals:
                self._steps(emit)
                return self._finish(emit, signals)
        finally:
            self._emit = lambda event: None
            close_all(subscribers)
            self.lock.release()

    def _compile_kernels(self, emit: Listener) -> None:
        """Compile (first run on a machine) or load the kernels before the first step, saying so when it compiles."""
        kernels = step_kernels(self.device, self.config.compensation.appearance)
        pending = modules_to_compile(kernels, self.device)
        if pending:
            emit(KernelsCompiling(modules=pending))
        compile_kernels(kernels, self.device)

    def _steps(self, emit: Listener) -> None:
        config, control, team, state = self.config, self.control, self.team, self.state
        n = team.world_size
        while not self.planner.finished(state.step, state.wall_seconds):
            control.wait_while_paused()
            started = time.perf_counter()
            with control.lock:
                tick = time.perf_counter()
                plan = self.plan
                state.strategy.follow(plan.schedule_for(config.strategy))
                view_index = team.pick(state.sampler.take(n))
                view = self.scene.train[view_index]
                for index in state.sampler.upcoming(PREFETCH_VIEWS * n)[team.rank::n]:  # decode ahead when images
                    self.scene.train[index].prefetch()                                   # are not all in memory
                count, scale = state.model.num_gaussians, plan.resolution_at(state.step)
                done = train_step(state.step, state.model, state.optimizers, state.strategy, view, config=config,
                                  plan=plan, scene_radius=self.scene.radius, background=self.background,
                                  device=self.device, reduce=self.requests.reduce, modules=state.modules,
                                  loss_terms=state.loss_terms, view_index=view_index)
                if changed(done.refine):
                    emit(RefineDone(step=state.step, report=done.refine))
                state.step += 1
                seconds = time.perf_counter() - tick
                state.train_seconds += seconds
                step = state.step
                team.check_identical(state.model, step)
                if config.eval_every and self.scene.test and step % config.eval_every == 0 and step < plan.steps:
                    result = self._evaluate(plan.sh_degree_at(step - 1))
                    emit(EvalDone(step=step, psnr=result.psnr, ssim=result.ssim,
                                  num_gaussians=state.model.num_gaussians))
            state.wall_seconds += time.perf_counter() - started
            # Before StepDone, so that it carries the plan's steps (--budget measures the step and plans again).
            self.planner.after_step(seconds, count, scale, step=step, wall_seconds=state.wall_seconds,
                                    gaussians_now=state.model.num_gaussians)
            plan, emitted = self.plan, time.perf_counter()
            emit(StepDone(step=step, total_steps=plan.steps, loss=done.loss, train_psnr=done.train_psnr,
                          num_gaussians=state.model.num_gaussians, sh_degree=plan.sh_degree_at(step - 1),
                          train_seconds=state.train_seconds, refine=done.refine, resolution=scale))
            state.wall_seconds += time.perf_counter() - emitted
            if self.requests.stop():
                self.save_checkpoint()
                raise MCSplatError(f"stopped at step {step:,}; the checkpoint is saved: continue with "
                                   f"`{command_for(n)} train {config.data} --out {self.run_dir} --resume`")
            if self.requests.checkpoint() and self._saved_at != step:  # unless this step's periodic one is written
                self.save_checkpoint()

    def _evaluate(self, sh_degree: int, lpips_net: str | None = None, save_renders: bool = False,
                  progress: bool = False) -> Evaluation:
        """The test views' scores, split between the processes (rank 0 writes the renders)."""
        render_file = (lambda name: self.folder.render_file("test", name)) if save_renders else None
        return evaluate(self.state.model, self.scene.test, self.background, sh_degree, self.device, lpips_net,
                        render_file, progress, team=self.team)

    def _finish(self, emit: Listener, signals: StopSignals) -> dict[str, Any]:
        """The last checkpoint, then the final evaluation, point_cloud.ply, metrics.json and RunFinished (the
        report); a signal after that checkpoint stops the run with one line that says how to finish it."""
        self.planner.end_at(self.state.step)  # --budget: what the last plan said, or fewer
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
        final_degree = self.plan.final_sh_degree(state.step)
        evaluation = None  # a scene without test views (--test-every 0) ends without test scores
        if self.scene.test:
            evaluation = self._evaluate(final_degree, lpips_net=config.lpips_net, save_renders=config.save_renders,
                                        progress=not config.quiet)
        seen = seen_in_views(state.model, self.scene.train, self.background, self.device, team)
        exported = self.folder.export_splats(state.model) if team.is_main else int(run_dir.alive(state.model).sum())
        strategy = state.strategy  # where growth stopped as the scene asked for no more, and the most allowed
        facts = RunFacts(exported_gaussians=exported, train_seconds=state.train_seconds,
                         wall_seconds=state.wall_seconds, device=str(self.device), strategy=config.strategy,
                         sh_degree=final_degree, processes=team.world_size,
                         invisible_gaussians=count_invisible(state.model, seen).as_dict(),
                         budget_seconds=self.planner.budget_seconds,
                         auto_cap=(strategy.chosen_cap, strategy.ceiling) if asks_the_scene(strategy) else None,
                         features=feature_facts(config, state.modules))
        record = metrics(evaluation, config.lpips_net, state.step, state.model.num_gaussians, facts)
        if team.is_main:
            self.folder.write_metrics(record)
        emit(RunFinished(run=self, metrics=record, evaluation=evaluation))
        return record
