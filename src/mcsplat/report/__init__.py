"""The run report: report.html (self-contained) and its PNG plots, for one run or a comparison of several.

`make_report([run_dir])` writes RUN/report.html and RUN/plots/*.png; `make_report([a, b, ...], out=DIR)` compares
runs on the same plots. ReportWriter makes it at the end of every training run (a subscriber, run/events.py). When
the run folder holds a mesh (RUN/mesh.ply, from `mcsplat export --format mesh`, which remakes the report), the report
pictures it from a few test views (mesh.py).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from PIL import Image
from tqdm import tqdm

from ..errors import MCSplatError
from ..run.events import RunFinished, Subscriber
from ..io.atomic import atomic_write_bytes, atomic_write_text
from ..run.folder import RunDir
from . import plots
from .mesh import mesh_figure_rows
from .runs import RunRecord, load_run

GRID_VIEWS = 6  # test views in the render / ground-truth grid, worst PSNR first

RenderView = Callable[[object], np.ndarray]  # a test View -> its render as uint8 [H, W, 3]


def grid_rows(run: RunRecord, test_views: Sequence, render_view: RenderView | None) -> list:
    """(name, PSNR, render, ground truth) of the worst test views: renders from RUN/renders/test/ when they were
    saved, else from `render_view`."""
    by_name = {view.name: view for view in test_views}
    rows = []
    for name, value in sorted(run.per_view_psnr.items(), key=lambda item: item[1])[:GRID_VIEWS]:
        view = by_name.get(name)
        if view is None:
            continue
        saved = RunDir(run.path).render_file("test", name)
        if saved.is_file():
            rendered = np.asarray(Image.open(saved).convert("RGB"))
        elif render_view is not None:
            rendered = render_view(view)
        else:
            continue
        rows.append((Path(name).stem, value, rendered, view.image.numpy()))
    return rows


def make_report(run_dirs: Sequence[Path], out: Path | None = None, test_views: Sequence = (),
                render_view: RenderView | None = None) -> Path:
    """Write report.html and plots/*.png into `out` (default: the run directory for one run); returns the page."""
    runs = [load_run(Path(d)) for d in run_dirs]
    if not runs:
        raise MCSplatError("no run directory given")
    if out is None:
        if len(runs) > 1:
            raise MCSplatError("comparing runs: pass --out DIR for the comparison report")
        out = runs[0].path
    figures = [("quality", "Test PSNR and SSIM over steps (star: final evaluation)", plots.quality(runs)),
               ("loss", "Training loss", plots.loss(runs)),
               ("gaussians", "Number of Gaussians", plots.gaussians(runs)),
               ("refinement", "Relocated / added (MCMC) or cloned / split (ADC) and pruned Gaussians per log record",
                plots.refinement(runs)),
               ("distributions", "Opacity and scale distributions of the final Gaussians", plots.distributions(runs)),
               ("step_time", "Time per training step", plots.step_time(runs))]
    if len(runs) == 1:
        rows = grid_rows(runs[0], test_views, render_view)
        if rows:
            names = ", ".join(f"{name} {value:.2f} dB" for name, value, _, _ in rows)
            figures.append(("test_views", f"Test views, worst PSNR first ({names}): render (left) and ground truth "
                            f"(right)", plots.view_grid(rows)))
        caption, panels = mesh_figure_rows(runs[0].path, test_views, render_view)
        if panels:
            figures.append(("mesh", caption, plots.image_grid(panels)))
    folder = RunDir(out)  # a run folder, or a comparison's folder laid out the same way
    for name, _, png in figures:
        atomic_write_bytes(folder.plots_folder / f"{name}.png", png)
    title = f"mcsplat report: {runs[0].name}" if len(runs) == 1 else "mcsplat comparison: " + \
        " vs ".join(run.name for run in runs)
    from .page import render_page
    page = folder.report_file
    atomic_write_text(page, render_page(title, runs, figures))
    return page


class ReportWriter(Subscriber):
    """Writes RUN/report.html when a training run finishes, and says so (with --quiet too: a file written)."""

    def on_run_finished(self, event: RunFinished) -> None:
        try:
            page = self._write(event)
        except Exception as error:  # the run's results are saved already: a failed report must not fail the run
            warnings.warn(f"report.html not written ({error}); make it with `mcsplat report {event.run.run_dir}`",
                          RuntimeWarning, stacklevel=2)
            return
        tqdm.write(f"wrote {page}")

    def _write(self, event: RunFinished) -> Path:
        import torch

        from ..data.images import uint8_pixels
        from ..render import render

        run = event.run

        @torch.no_grad()
        def render_view(view) -> np.ndarray:
            return uint8_pixels(render(run.model, view.camera.to(run.device), run.background,
                                       event.metrics["sh_degree"]).rgb)

        return make_report([run.run_dir], test_views=run.scene.test, render_view=render_view)
