"""Training speed with the live viewer open in a browser against without it (issue 12: at least 80%).

Trains the bundled lego demo with the `make demo` model size twice, the same steps and seed: once alone, once with
the viewer serving a headless Chromium (tests/support/browser.py) that stays connected, so that the viewer re-renders
the changing model all the time at its bounded rate. Speed is wall-clock steps per second after a warm-up. On a machine
without a GPU the browser's software WebGL also takes CPU from training, so this is a pessimistic figure.

    .venv/bin/python benchmarks/viewer_overhead.py [--steps 400] [--threads N]
"""

from __future__ import annotations

import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import tyro

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "support"))

from browser import Browser  # noqa: E402

from mcsplat.config import ModelConfig, TrainConfig  # noqa: E402
from mcsplat.run.events import StepDone, Subscriber  # noqa: E402
from mcsplat.strategy.mcmc import MCMCConfig  # noqa: E402
from mcsplat.train import train  # noqa: E402
from mcsplat.viewer import TrainingViewer  # noqa: E402

WARMUP = 50


@dataclass(frozen=True)
class Options:
    """Training speed with the live viewer open in a browser against without it."""

    steps: int = 400
    """Training steps of each run."""
    threads: int | None = None
    """CPU threads of the training (default: all cores)."""
    size: str = "1280x720"
    """Browser window, WIDTHxHEIGHT."""


class StepClock(Subscriber):
    def __init__(self):
        self.times: dict[int, float] = {}

    def on_step_done(self, event: StepDone) -> None:
        self.times[event.step] = time.perf_counter()

    def steps_per_second(self) -> float:
        last = max(self.times)
        return (last - WARMUP) / (self.times[last] - self.times[WARMUP])


class BrowserOnStart(Subscriber):
    """Opens the viewer's page in a headless browser as soon as the server is up, and waits for its first image."""

    def __init__(self, viewer: TrainingViewer, width: int, height: int):
        self.viewer, self.size, self.browser = viewer, (width, height), None

    def on_run_started(self, event) -> None:
        self.browser = Browser(*self.size)
        self.browser.call("Page.navigate", url=self.viewer.server.url)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not self.frames()[0]:
            time.sleep(0.2)

    def frames(self) -> tuple[int, float]:
        """Images pushed so far and seconds spent rendering them."""
        renderers = list(self.viewer.server.renderers.values()) if self.viewer.server else []
        return sum(r.frames for r in renderers), sum(r.render_seconds for r in renderers)

    def close(self) -> None:
        if self.browser is not None:
            self.browser.close()


def config(out: Path, steps: int, threads: int | None) -> TrainConfig:
    return TrainConfig(data=REPO / "data" / "lego_demo", out=out, steps=steps, quiet=True, save_every=0,
                       save_renders=False, lpips_net="alex", threads=threads,
                       model=ModelConfig(num_init_points=10_000),
                       mcmc=MCMCConfig(cap_max=20_000, refine_start=200, refine_every=50))


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    width, height = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        alone = StepClock()
        train(config(Path(tmp) / "alone", args.steps, args.threads), subscribers=[alone])
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        viewer = TrainingViewer(port=port, quiet=True)
        watched, browser = StepClock(), None
        browser = BrowserOnStart(viewer, width, height)
        frames = {}

        class CountFrames(Subscriber):
            def on_step_done(self, event):
                frames[event.step] = browser.frames()

        train(config(Path(tmp) / "viewer", args.steps, args.threads),
              subscribers=[viewer, browser, watched, CountFrames()])
    a, b = alone.steps_per_second(), watched.steps_per_second()
    seconds = watched.times[max(watched.times)] - watched.times[WARMUP]
    rendered = frames[max(frames)][0] - frames[WARMUP][0]
    render_seconds = frames[max(frames)][1] - frames[WARMUP][1]
    print(f"without viewer: {a:.2f} steps/s; with the viewer open in a browser ({width}x{height}): {b:.2f} steps/s "
          f"= {b / a:.0%}; the viewer pushed {rendered} images in {seconds:.0f} s ({rendered / seconds:.1f}/s), "
          f"{render_seconds:.1f} s of them rendering")


if __name__ == "__main__":
    main()
