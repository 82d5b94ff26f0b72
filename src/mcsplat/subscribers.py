"""The run's standard consumers (see run/events.py): progress bar, console messages, log.jsonl, periodic checkpoints
and a --surface run's mesh.

Each is small and knows only the events it listens to; train.train() subscribes them to every run.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from .data.attachments import masks
from .run.events import CheckpointWritten, EvalDone, KernelsCompiling, RunFinished, RunStarted, StepDone, Subscriber
from .io.disk import writing_into
from .metrics import LPIPS_HINT
from .run.folder import RunDir
from .visibility import describe

LOG_EVERY = 100  # steps between two log.jsonl records


class ProgressBar(Subscriber):
    """tqdm bar over the steps, with loss, train PSNR and the number of Gaussians every 10 steps."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.bar: tqdm | None = None

    def on_run_started(self, event: RunStarted) -> None:
        self.bar = tqdm(total=event.run.plan.steps, initial=event.start_step, disable=self.quiet,
                        dynamic_ncols=True, unit="step", mininterval=0.5)

    def on_step_done(self, event: StepDone) -> None:
        if self.bar.total != event.total_steps:  # --budget plans the steps as it goes
            self.bar.total = event.total_steps
        self.bar.update(1)
        if event.step % 10 == 0 or event.step == event.total_steps:
            self.bar.set_postfix(loss=f"{event.loss:.4f}", psnr=f"{event.train_psnr:.2f}",
                                 gaussians=event.num_gaussians, refresh=False)
        if event.step == event.total_steps:
            self.close()  # before the final evaluation's own progress and messages

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class ConsoleLog(Subscriber):
    """One line when the run starts, after each periodic evaluation and at the end. With --quiet only the final
    scores and the files written: what a script running it still wants."""

    def __init__(self, quiet: bool):
        self.write: Callable[[str], None] = (lambda text: None) if quiet else tqdm.write
        self.result: Callable[[str], None] = tqdm.write

    def on_run_started(self, event: RunStarted) -> None:
        run = event.run
        scene, config, plan = run.scene, run.config, run.plan
        processes = run.world_size
        steps = f"{plan.steps:,} steps" + (f" of {processes} views ({processes} processes)" if processes > 1 else "")
        if config.budget is not None:
            steps = f"a {config.budget} budget (steps, cap and resolution planned as it runs)"
        self.write(f"mcsplat: {scene.kind} scene {scene.root.name}: {len(scene.train)} train / {len(scene.test)} "
                   f"test views, {config.strategy} strategy, init {event.init_note}, {steps} on {run.device}")
        for note in scene.notes:
            if note.startswith(masks.NOTE_PREFIX):  # what the loss leaves out is not something to find out later
                self.write(f"mcsplat: {note}")

    def on_kernels_compiling(self, event: KernelsCompiling) -> None:
        self.write(f"compiling {event.modules} kernel module(s) for this machine (once: later runs load them from "
                   "Warp's kernel cache)...")

    def on_eval_done(self, event: EvalDone) -> None:
        self.write(f"step {event.step:,}: test PSNR {event.psnr:.2f} dB, SSIM {event.ssim:.4f}, "
                   f"{event.num_gaussians:,} Gaussians")

    def on_run_finished(self, event: RunFinished) -> None:
        m, evaluation = event.metrics, event.evaluation
        if evaluation is None:
            self.result(f"no test views (--test-every {event.run.config.test_every}), so no test scores; "
                        f"{m['num_gaussians']:,} Gaussians, {m['train_seconds']:.0f} s of training")
        else:
            lpips_text = f"{evaluation.lpips:.4f}" if evaluation.lpips is not None else "n/a"
            self.result(f"test PSNR {evaluation.psnr:.2f} dB, SSIM {evaluation.ssim:.4f}, LPIPS-{m['lpips_net']} "
                        f"{lpips_text} on {evaluation.views} views; {m['num_gaussians']:,} Gaussians, "
                        f"{m['train_seconds']:.0f} s of training")
        if m.get("auto_cap") is not None and m["auto_cap"] < m["auto_cap_ceiling"]:
            self.write(f"growth stopped at {m['auto_cap']:,} Gaussians, where the views asked for no more (at most "
                       f"{m['auto_cap_ceiling']:,}; --mcmc.relocation paper grows to --cap-max whatever)")
        if m.get("compensated_psnr") is not None and event.run.config.compensation.appearance != "none":
            self.result(f"compensated (each test view's colour transform fitted on its left half, the right half "
                        f"scored): PSNR {m['compensated_psnr']:.2f} dB, SSIM {m['compensated_ssim']:.4f}")
        if "pose_corrections" in m:
            c = m["pose_corrections"]
            self.write(f"pose corrections learned: median {c['median_degrees']:.3f} deg and {c['median_radii']:.4f} "
                       f"scene radii, largest {c['max_degrees']:.3f} deg and {c['max_radii']:.4f} radii")
        if evaluation is not None and evaluation.masked_views:
            self.result(f"over the pixels the masks keep: PSNR {evaluation.masked_psnr:.2f} dB, SSIM "
                        f"{evaluation.masked_ssim:.4f} on {evaluation.masked_views} views")
        if "budget_seconds" in m:
            self.write(f"budget: {m['steps']:,} steps in {m['wall_seconds']:.0f} s of the {m['budget_seconds']:.0f} s "
                       "budget (set-up, the final evaluation and the export not counted)")
        if evaluation is not None and evaluation.lpips is None:
            self.write(f"hint: {LPIPS_HINT}")
        run_dir = RunDir(event.run.run_dir)
        self.result(f"wrote {run_dir.splats_file} ({m['exported_gaussians']:,} Gaussians) and {run_dir.metrics_file}")
        if m["invisible_gaussians"]["never_composited"]:
            self.write(f"{describe(m['invisible_gaussians'])}: `mcsplat export {run_dir.path} --prune` leaves them "
                       "out")


class LogWriter(Subscriber):
    """Appends to log.jsonl every LOG_EVERY steps (and at the last step) and at each periodic evaluation: step,
    loss, train PSNR, number of Gaussians, training seconds, refine counts since the previous record, test PSNR/SSIM.

    Counts are summed over the steps since the previous record; levels (the automatic cap's demand) keep their
    value at the last refine step (a sum over the refine steps since the previous record would read as ten times
    the share with refine steps every 10)."""

    def __init__(self, path: Path):
        self.path = path
        self.counts: dict[str, int] = {}
        self.evaluation: EvalDone | None = None

    def on_eval_done(self, event: EvalDone) -> None:
        self.evaluation = event  # StepDone of the same step follows and writes it

    def on_step_done(self, event: StepDone) -> None:
        if event.refine is not None:
            for key, value in event.refine.counts().items():
                self.counts[key] = self.counts.get(key, 0) + int(value)
            self.counts.update(event.refine.levels())
        record = None
        if event.step % LOG_EVERY == 0 or event.step == event.total_steps:
            record = {"step": event.step, "loss": round(event.loss, 6), "train_psnr": round(event.train_psnr, 3),
                      "num_gaussians": event.num_gaussians, "elapsed_seconds": round(event.train_seconds, 2),
                      "resolution": round(event.resolution, 4)}
            record.update(self.counts)
            self.counts = {}
        if self.evaluation is not None and self.evaluation.step == event.step:
            record = record or {"step": event.step, "num_gaussians": event.num_gaussians,
                                "elapsed_seconds": round(event.train_seconds, 2)}
            record.update(test_psnr=round(self.evaluation.psnr, 3), test_ssim=round(self.evaluation.ssim, 4))
            self.evaluation = None
        if record is not None:
            with writing_into(self.path.parent), open(self.path, "a") as f:
                f.write(json.dumps(record) + "\n")


class Checkpointer(Subscriber):
    """Saves the run's checkpoint every `every` steps, and asks for one when `minutes` have passed since the last
    (0 = never; the run saves at the end and on stop itself).

    Steps are the same on every process, so each saves at once; time is not, so a save by time is asked for through
    the run's Control and agreed between the processes with the next step (trainer.TrainingRun)."""

    def __init__(self, every: int, minutes: float = 0.0):
        self.every, self.minutes = every, minutes
        self.run = None
        self.last_save = 0.0  # time.monotonic() of the last checkpoint (or of the start)

    def on_run_started(self, event: RunStarted) -> None:
        self.run = event.run
        self.last_save = time.monotonic()

    def on_checkpoint_written(self, event: CheckpointWritten) -> None:
        self.last_save = time.monotonic()

    def on_step_done(self, event: StepDone) -> None:
        if event.step >= event.total_steps:
            return
        if self.every and event.step % self.every == 0:
            self.run.save_checkpoint()
        elif self.minutes and time.monotonic() - self.last_save >= 60.0 * self.minutes:
            self.run.control.request_checkpoint()


class MeshWriter(Subscriber):
    """RUN/mesh.ply when the run finishes (a --surface run's, before the report, which pictures it): the training
    views fused as `mcsplat export RUN --format mesh` fuses them, with its defaults. The run's results are saved by
    then, so a mesh that cannot be made warns and leaves the command to make it."""

    def __init__(self, quiet: bool):
        self.quiet = quiet

    def on_run_finished(self, event: RunFinished) -> None:
        from .mesh import MeshOptions, extract, write_mesh

        run = event.run
        path = RunDir(run.run_dir).mesh_file
        command = f"`mcsplat export {run.run_dir} --format mesh`"
        if run.world_size > 1:  # the other processes would wait for it at the run's last barrier
            tqdm.write(f"{path.name} is not made at the end of a run of several processes: make it with {command}")
            return
        started = time.perf_counter()
        try:
            mesh = extract(run.model, run.scene.train, MeshOptions(), sh_degree=event.metrics["sh_degree"],
                           progress=not self.quiet)
            write_mesh(path, mesh)
        except Exception as error:  # the run's results are saved: a mesh that fails (out of memory on a GPU, say)
            tqdm.write(f"warning: {path.name} not written ({error}); make it with {command}")  # must not fail it
            return
        tqdm.write(f"wrote {path} ({len(mesh.faces):,} faces, {time.perf_counter() - started:.0f} s)")
