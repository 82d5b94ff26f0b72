"""Make docs/viewer.png and docs/report.png: trains the bundled demo scene with the live viewer open in headless
Chromium, pauses it, photographs the page, lets the run finish and photographs its report.

    .venv/bin/python docs/screenshots.py [--steps 600]     (about a minute on 2 CPU cores)
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "support"))

from browser import Browser  # noqa: E402

from mcsplat.config import ModelConfig, TrainConfig  # noqa: E402
from mcsplat.run.events import Control  # noqa: E402
from mcsplat.strategy.mcmc import MCMCConfig  # noqa: E402
from mcsplat.train import train  # noqa: E402
from mcsplat.viewer import TrainingViewer  # noqa: E402

DISMISS_NOTICE = """[...document.querySelectorAll('button')].filter(b => b.closest('.mantine-Notification-root'))
    .forEach(b => b.click())"""


def click(browser: Browser, text: str) -> None:
    browser.evaluate(f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {text!r}).click()")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=600)
    args = parser.parse_args()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer, control = TrainingViewer(port=port, quiet=True), Control()
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "lego_demo"
        config = TrainConfig(data=REPO / "data" / "lego_demo", out=run, steps=args.steps, quiet=True, save_every=0,
                             eval_every=200, lpips_net="alex", sh_increase_every=150,
                             model=ModelConfig(num_init_points=10_000),
                             mcmc=MCMCConfig(cap_max=20_000, refine_start=100, refine_every=50))
        trainer = threading.Thread(target=train, args=(config,), kwargs=dict(subscribers=[viewer], control=control))
        trainer.start()
        browser = None
        try:
            while viewer.server is None:
                time.sleep(0.2)
            browser = Browser(1280, 800)
            browser.call("Page.navigate", url=viewer.server.url)
            browser.wait_for("document.body.innerText.includes('steps/s')", timeout=120)
            while viewer.step < args.steps - 100:
                time.sleep(0.5)
            click(browser, "Pause training")
            browser.wait_for("document.body.innerText.includes('Resume training')")
            browser.evaluate(DISMISS_NOTICE)
            time.sleep(3.0)  # the full-resolution image
            browser.screenshot(REPO / "docs" / "viewer.png")
            click(browser, "Resume training")
            trainer.join()
            browser.call("Page.navigate", url=(run / "report.html").as_uri())
            browser.wait_for("document.readyState === 'complete'")
            browser.call("Emulation.setDeviceMetricsOverride", width=1280, height=2400, deviceScaleFactor=1,
                         mobile=False)
            time.sleep(0.5)
            browser.screenshot(REPO / "docs" / "report.png")
        finally:
            control.stop()
            trainer.join()
            if browser is not None:
                browser.close()
    print("wrote docs/viewer.png and docs/report.png")


if __name__ == "__main__":
    main()
