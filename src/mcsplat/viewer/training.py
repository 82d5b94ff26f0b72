"""The viewer as a subscriber of a training run (run/events.py): shows the model as it trains, steers pause / resume."""

from __future__ import annotations

import time
from typing import Sequence

from ..run.events import EvalDone, RunFinished, RunStarted, StepDone, Subscriber
from .server import ViewerServer

STATS_INTERVAL = 0.25  # seconds between two updates of the panel's numbers


class TrainingViewer(Subscriber):
    def __init__(self, host: str = "127.0.0.1", port: int = 8080, quiet: bool = False, origins: Sequence[str] = ()):
        self.host, self.port, self.quiet, self.origins = host, port, quiet, origins
        self.server: ViewerServer | None = None
        self.test_psnr: float | None = None
        self.last_stats = (0.0, 0)  # (wall time, step) of the last panel update
        self.steps_per_second = 0.0
        self.step = 0
        self.last_step: StepDone | None = None
        self.control = None

    def on_run_started(self, event: RunStarted) -> None:
        run = event.run
        control = run.control
        self.control = control

        def pause(paused: bool) -> None:
            control.pause() if paused else control.resume()
            if paused and self.last_step is not None:  # show where it stopped, not the last 4 Hz update
                self.server.set_stats(self._stats(self.last_step))

        self.server = ViewerServer(self.host, self.port, lock=control.lock, scene_radius=run.scene.radius,
                                   background=run.background, max_sh_degree=run.config.model.sh_degree,
                                   training=True, quiet=self.quiet, on_pause=pause, origins=self.origins)
        self.server.add_cameras([view.camera for view in run.scene.train])
        self.server.set_model(run.model)
        self.last_stats = (time.monotonic(), event.start_step)
        self.step = event.start_step

    def on_eval_done(self, event: EvalDone) -> None:
        self.test_psnr = event.psnr

    def on_step_done(self, event: StepDone) -> None:
        self.step, self.last_step = event.step, event
        self.server.training_sh_degree = event.sh_degree
        self.server.touch()
        now = time.monotonic()
        then, step_then = self.last_stats
        if now - then >= STATS_INTERVAL or event.step == event.total_steps or self.control.paused:
            self.steps_per_second = (event.step - step_then) / max(now - then, 1e-9)
            self.last_stats = (now, event.step)
            self.server.set_stats(self._stats(event))

    def on_run_finished(self, event: RunFinished) -> None:
        self.server.training = False
        self.server.pause_button.visible = self.server.resume_button.visible = False
        self.test_psnr = event.metrics["psnr"]
        test = f"{self.test_psnr:.2f} dB" if self.test_psnr is not None else "n/a (no test views)"
        self.server.set_stats(f"**finished** at step {self.step:,}  \nfinal test PSNR {test}  \n"
                              f"{event.metrics['num_gaussians']:,} Gaussians")

    def _stats(self, event: StepDone) -> str:
        test = f"{self.test_psnr:.2f} dB" if self.test_psnr is not None else "n/a"
        return (f"**step** {event.step:,} / {event.total_steps:,}  \n"
                f"loss {event.loss:.4f}, train PSNR {event.train_psnr:.2f} dB  \n"
                f"test PSNR {test}  \n{event.num_gaussians:,} Gaussians  \n"
                f"{self.steps_per_second:.1f} steps/s")

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
            self.server = None
