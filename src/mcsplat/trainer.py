"""The training loop: the run (`TrainingRun`) that repeats one step (step.py's `Step`), emitting run/events.py's events.

Where the run's files go is run/folder.py's business, how its state starts and what a checkpoint holds run/state.py's,
what the run decides (its steps, schedules and cap) its planner's (planning/), scoring run/evaluation.py's and
metrics.json's layout run/metrics.py's; train.py puts a run together with its consumers.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

from .run import folder as run_dir
from .run import start as run_start
from .compute.compile import compile_kernels, modules_to_compile
from .config import TrainConfig
from .distributed import SingleProcess, Team, command_for
from .errors import MCSplatError
from .run.evaluation import Evaluation, evaluate, seen_in_views
from .run.events import (CheckpointWritten, Control, EvalDone, KernelsCompiling, Listener, RefineDone, RunFinished,
                     RunStarted, StepDone, close_all)
from .gaussians import GaussianModel
from .io.lock import FolderLock
from .optim import update_for
from .planning import Plan, run_record
from .render import forget_pair_rooms
from .run.metrics import RunFacts, metrics
from .run.setup import set_up
from .run.state import feature_facts
from .step import Step, alone, step_kernels
from .graphed_step import graphed
from .stopping import AgreedRequests, StopSignals
from .strategy.base import asks_the_scene, changed
from .visibility import count_invisible

PREFETCH_VIEWS = 2  # images decoded in the background ahead of their step (a no-op when all are in memory)
CHECK_LOSS_EVERY = 10  # steps between two reads of whether the loss stayed finite (and before a checkpoint)


class TrainingRun:
    """A training job: set up (or resumed) from its configuration, then `run(subscribers)` steps it to the end,
    emitting the events of run/events.py (it is their RunView). `control` pauses or stops it from another thread.

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
        state = self.state
        reduce = self.requests.reduce if team.world_size > 1 else alone
        self.one_step = graphed(Step(state.model, state.optimizers, state.strategy, self.config, self.scene.radius,
                                     self.background, self.device, reduce=reduce, modules=state.modules,
                                     loss_terms=state.loss_terms, update=update_for(self.device, team.world_size)),
                                self.config.cuda_graph)
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
        self.one_step.check_finite()  # never a checkpoint of a model a loss that was not finite has stepped
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
            self.planner.begin(self.state, self.scene, self.one_step)
            forget_pair_rooms()  # rooms for this model's pair lists, not --budget's probes' or an earlier run's
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
                state.strategy.follow(plan.schedule)
                view_index = team.pick(state.sampler.take(n))
                view = self.scene.train[view_index]
                for index in state.sampler.upcoming(PREFETCH_VIEWS * n)[team.rank::n]:  # decode ahead when images
                    self.scene.train[index].prefetch()                                   # are not all in memory
                count, scale = state.model.num_gaussians, plan.resolution_at(state.step)
                done = self.one_step(state.step, view, plan, view_index)
                if self.planner.budget_seconds is not None:  # a plan on the clock times the device's work,
                    done.values.read()                       # not how long queueing it took
                if (state.step + 1) % CHECK_LOSS_EVERY == 0 or state.step + 1 >= plan.steps:  # the last one logs
                    self.one_step.check_finite()
                if changed(done.refine):
                    emit(RefineDone(step=state.step, report=done.refine))
                state.step += 1
                seconds = time.perf_counter() - tick
                state.train_seconds += seconds
                step = state.step
                team.check_identical(state.model, step)
                if config.eval_every and self.scene.test and step % config.eval_every == 0 and step < plan.steps:
                    self.one_step.check_finite()  # no scores of a model a loss that was not finite has stepped
                    result = self._evaluate(plan.sh_degree_at(step - 1))
                    emit(EvalDone(step=step, psnr=result.psnr, ssim=result.ssim,
                                  num_gaussians=state.model.num_gaussians))
            state.wall_seconds += time.perf_counter() - started
            # Before StepDone, so that it carries the plan's steps (--budget measures the step and plans again).
            self.planner.after_step(seconds, count, scale, step=step, wall_seconds=state.wall_seconds,
                                    gaussians_now=state.model.num_gaussians)
            plan, emitted = self.plan, time.perf_counter()
            emit(StepDone(step=step, total_steps=plan.steps, values=done.values,
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
