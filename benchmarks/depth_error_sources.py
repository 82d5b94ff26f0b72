"""Where lego's depth error comes from, for runs that depth_accuracy.py trained: the truth's noise, how the scorer
samples a pixel, the estimator that turns a pixel's Gaussians into one depth, or the Gaussians themselves.

    .venv/bin/python benchmarks/depth_error_sources.py                   # the mcmc-surface-antialiased run, 20 views
    .venv/bin/python benchmarks/depth_error_sources.py --views 40 \
        --runs benchmarks/results/depth_accuracy/runs/mcmc-2000 benchmarks/results/depth_accuracy/runs/adc-2000

Over an evenly spaced subset of the test views, scored as depth_accuracy.py scores them (pixels where the truth has
depth and the model's alpha is at least 0.5; all of them, and those away from depth edges), each row changes one
thing:

    median depth          what depth_accuracy.py scores (and the mesh export fuses)
    2x2 area average      the median depth rendered at twice the size and averaged over each pixel's four, as the
                          dataset's 400x400 depth was made from its 800x800 renders (INTER_AREA) away from the
                          outline (at the outline the dataset averaged in the background's code, which this does not)
    alpha window A-B      instead of the one Gaussian at which the accumulated alpha reaches 0.5, the mean of the
                          Gaussians' depths (each where the pixel's ray meets its density's peak, as the median's)
                          weighted by the share of the accumulated alpha between A and B each one adds; 0-1 is the
                          alpha-weighted mean of those depths
    truth smoothed        the median depth against the truth averaged over 3x3 pixels (its 8-bit steps of 0.031
                          units averaged down; meaningful away from edges only)

If no row but the last moves the error, the estimator and the sampling are not what limits it: the Gaussians are.
Results to results/depth_accuracy/error_sources.md.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import tyro

import _common as C
import depth_accuracy

WINDOWS = ((0.4, 0.6), (0.2, 0.8), (0.0, 1.0))


@dataclass(frozen=True)
class Options:
    """The sources of lego's depth error, row by row."""

    runs: tuple[Path, ...] = (C.RESULTS / "depth_accuracy" / "runs" / "mcmc-surface-antialiased-2000",)
    """Runs that depth_accuracy.py trained."""
    views: int = 20
    """Test views scored, evenly spaced over the 200."""
    data_root: Path = C.DATA_ROOT


class CompositeInputs:
    """A render path that keeps what the compositing was handed (the projected Gaussians and their tile lists)."""

    def __init__(self):
        from mcsplat.render.paths import KERNEL_PATH, RenderPath

        self.kept: tuple = ()
        self.path = RenderPath(KERNEL_PATH.project, KERNEL_PATH.bin, self._composite)
        self._inner = KERNEL_PATH.composite

    def _composite(self, *args, **kwargs):
        self.kept = args
        return self._inner(*args, **kwargs)


def window_depths(model, camera, sh_degree: int, windows=WINDOWS
                  ) -> tuple[object, dict[tuple[float, float], torch.Tensor], torch.Tensor]:
    """The render (with its median depth); per alpha window, each pixel's window-weighted mean depth [H, W] (0 where
    the window holds none of its alpha); and the accumulated alpha [H, W] that this loop found, the render's own."""
    from mcsplat.render import render
    from mcsplat.render.constants import ALPHA_MAX, ALPHA_MIN, TILE_SIZE, TRANSMITTANCE_MIN
    from mcsplat.render.outputs.median import peak_depths, pixel_rays

    inputs = CompositeInputs()
    out = render(model, camera, None, sh_degree, outputs={"median_depth"}, path=inputs.path)
    means2d, conics, opacities, _, _, _, bins, width, height = inputs.kept[:9]
    bins = bins.listed()
    maps = {window: torch.zeros(height, width, dtype=torch.float64) for window in windows}
    accumulated = torch.zeros(height, width, dtype=torch.float64)
    rows, columns = torch.meshgrid(torch.arange(TILE_SIZE), torch.arange(TILE_SIZE), indexing="ij")
    for tile in range(bins.tiles_x * bins.tiles_y):
        start, end = (int(v) for v in bins.tile_ranges[tile])
        if end <= start:
            continue
        ids = bins.gaussian_ids[start:end].long()  # front to back
        x = (tile % bins.tiles_x * TILE_SIZE + columns).reshape(-1)
        y = (tile // bins.tiles_x * TILE_SIZE + rows).reshape(-1)
        inside = (x < width) & (y < height)
        dx = x[:, None] + 0.5 - means2d[ids, 0].double()
        dy = y[:, None] + 0.5 - means2d[ids, 1].double()
        a, b, c = conics[ids].double().unbind(1)
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = torch.clamp(opacities[ids].double() * torch.exp(power), max=ALPHA_MAX)
        alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
        after = torch.cumprod(1 - alpha, dim=1)
        alpha = torch.where(after >= TRANSMITTANCE_MIN, alpha, torch.zeros_like(alpha))  # where the kernels stop
        accumulated_after = 1 - torch.cumprod(1 - alpha, dim=1)
        accumulated_before = torch.cat([torch.zeros_like(alpha[:, :1]), accumulated_after[:, :-1]], dim=1)
        # Each Gaussian's depth where the pixel's ray meets its density's peak, as the median depth takes it.
        depth = peak_depths(ids.repeat(len(x)), pixel_rays(y, x, camera).repeat_interleave(len(ids), dim=0),
                            model.means, model.quats, model.scales, camera).reshape(len(x), len(ids))
        accumulated[y[inside], x[inside]] = accumulated_after[inside, -1]
        for low, high in windows:
            share = (accumulated_after.clamp(max=high) - accumulated_before.clamp(min=low)).clamp(min=0)
            total = share.sum(dim=1)
            mean = torch.where(total > 0, (share * depth).sum(dim=1) / total.clamp(min=1e-12), torch.zeros_like(total))
            maps[(low, high)][y[inside], x[inside]] = mean[inside]
    return out, maps, accumulated


def area_averaged_median(model, camera, sh_degree: int) -> torch.Tensor:
    """The median depth rendered at twice the size, averaged over each pixel's four where they are covered."""
    from mcsplat.render import render

    big = render(model, camera.scaled(2 * camera.width, 2 * camera.height), None, sh_degree,
                 outputs={"median_depth"})
    seen = (big.alpha >= depth_accuracy.ALPHA_SEEN).double()
    summed = F.avg_pool2d((big.median_depth.double() * seen)[None, None], 2)[0, 0]
    count = F.avg_pool2d(seen[None, None], 2)[0, 0]
    return torch.where(count > 0, summed / count.clamp(min=1e-12), torch.zeros_like(summed))


def figures(errors: list[np.ndarray]) -> dict:
    signed = np.concatenate(errors)
    values = np.abs(signed)
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
            "within": float((values <= depth_accuracy.WITHIN).mean()), "bias": float(np.median(signed))}


@torch.no_grad()
def sources(run: Path, views) -> list[dict]:
    from mcsplat.run.trained import load

    trained = load(run, torch.device("cpu"))
    rows: dict[str, tuple[list, list]] = {}

    def add(name: str, estimate: torch.Tensor, truth: torch.Tensor, both, interior) -> None:
        error = (estimate.double() - truth.double())
        kept = rows.setdefault(name, ([], []))
        kept[0].append(error[both].numpy())
        kept[1].append(error[interior].numpy())

    for view in views:
        truth = view.attachment("depth")[..., 0]
        out, windows, _ = window_depths(trained.model, view.camera, trained.sh_degree)
        both = (truth > 0) & (out.alpha >= depth_accuracy.ALPHA_SEEN)
        interior = both & depth_accuracy.away_from_edges(truth)
        add("median depth", out.median_depth, truth, both, interior)
        add("2x2 area average", area_averaged_median(trained.model, view.camera, trained.sh_degree), truth, both,
            interior)
        for (low, high), estimate in windows.items():
            add(f"alpha window {low:g}-{high:g}", estimate, truth, both, interior)
        smoothed = F.avg_pool2d(truth[None, None].double(), 3, stride=1, padding=1)[0, 0]
        add("truth smoothed 3x3", out.median_depth, smoothed, both, interior)
    return [{"run": run.name, "row": name, "views": len(views), "all": figures(everywhere),
             "away_from_edges": figures(interior)} for name, (everywhere, interior) in rows.items()]


def main() -> None:
    options = tyro.cli(Options, description=__doc__)
    lego = C.scene_path("lego", options.data_root)
    views = depth_accuracy.scored_views(lego)
    views = views[::max(1, len(views) // options.views)][:options.views]
    records = []
    for run in options.runs:
        for record in sources(Path(run), views):
            record.update(commit=C.git_commit(), date=C.timestamp())
            C.emit(record)
            records.append(record)
    columns = [("run", "run", ""), ("row", "row", ""), ("views", "views", "")]
    for part, label in (("all", ""), ("away_from_edges", "away from edges: ")):
        columns += [(f"{label}median", part, lambda r, p=part: f"{r[p]['median']:.4f}"),
                    (f"{label}p90", part, lambda r, p=part: f"{r[p]['p90']:.4f}"),
                    (f"{label}within 0.02", part, lambda r, p=part: f"{100 * r[p]['within']:.1f}%")]
    page = ["# Where lego's depth error comes from", "",
            f"`.venv/bin/python benchmarks/depth_error_sources.py {' '.join(sys.argv[1:])}`".replace(" `", "`"),
            "", "The module docstring says what each row changes.",
            "", C.markdown_table(records, columns), ""]
    C.write_text(C.RESULTS / "depth_accuracy" / "error_sources.md", "\n".join(page))
    print(page[-2])


if __name__ == "__main__":
    main()
