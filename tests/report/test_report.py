"""The run report: written by every training run, every embedded image decodes, the grid lists the worst test views
first; `mcsplat report` remakes it and compares runs."""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

from PIL import Image

from mcsplat.cli import main
from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.train import train

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"
PLOTS = {"quality", "loss", "gaussians", "refinement", "distributions", "step_time"}


def embedded_images(page: Path) -> dict[str, Image.Image]:
    text = page.read_text()
    assert "http://" not in text and "https://" not in text, "the report must not need the network"
    images = {}
    for alt, data in re.findall(r"<img alt='([^']+)' src='data:image/png;base64,([^']+)'>", text):
        image = Image.open(io.BytesIO(base64.b64decode(data)))
        image.load()  # decodes every pixel: a damaged PNG raises here
        images[alt] = image
    return images


def test_every_run_writes_a_self_contained_report(tiny_run):
    page = tiny_run / "report.html"
    images = embedded_images(page)
    assert set(images) == PLOTS | {"test_views"}
    for name in images:
        assert (tiny_run / "plots" / f"{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    worst = sorted(metrics["per_view_psnr"].items(), key=lambda item: item[1])[:6]
    caption = re.search(r"worst PSNR first \(([^)]*)\)", page.read_text()).group(1)
    assert caption == ", ".join(f"{Path(name).stem} {value:.2f} dB" for name, value in worst)
    assert f"{metrics['psnr']:.2f}" in page.read_text()
    assert images["test_views"].height > 5 * images["test_views"].width / 2.5, "six rows of render | ground truth"


def test_report_command_remakes_it_and_compares_runs(tiny_run, tmp_path, capsys):
    adc = tmp_path / "adc"
    train(TrainConfig(data=DEMO, out=adc, steps=20, quiet=True, strategy="adc", lpips_net="alex", save_every=0,
                      save_renders=False, model=ModelConfig(num_init_points=1000)))
    (adc / "report.html").unlink()
    assert main(["report", str(adc)]) == 0
    # Renders were not saved: the grid is rendered from the checkpoint.
    assert set(embedded_images(adc / "report.html")) == PLOTS | {"test_views"}
    assert main(["report", str(tiny_run), str(adc), "--out", str(tmp_path / "cmp")]) == 0
    page = (tmp_path / "cmp" / "report.html").read_text()
    assert set(embedded_images(tmp_path / "cmp" / "report.html")) == PLOTS
    assert "run (mcmc)" in page and "adc (adc)" in page
    capsys.readouterr()
    assert main(["report", str(tiny_run), str(adc)]) == 2
    assert "--out" in capsys.readouterr().err
