"""The report's plots as PNG bytes (matplotlib's object API, no pyplot: no global state, safe in any thread).

Each function takes one or more RunRecords and draws one line (or histogram) per run, so the same code makes a
single run's report and a comparison of runs.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.figure import Figure

from .runs import DEAD_OPACITY, RunRecord

WIDTH, HEIGHT, DPI = 6.4, 3.6, 100


def _png(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, bbox_inches="tight")
    return buffer.getvalue()


def _axes(title: str, xlabel: str, ylabel: str, panels: int = 1):
    figure = Figure(figsize=(WIDTH * (1 + 0.6 * (panels - 1)), HEIGHT))
    axes = figure.subplots(1, panels, squeeze=False)[0]
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
    figure.suptitle(title)
    return figure, axes


def _legend(ax) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)


def quality(runs: list[RunRecord]) -> bytes:
    """Test PSNR and SSIM over steps (periodic evaluations, then the final one marked), final LPIPS in the legend."""
    figure, (left, right) = _axes("Test quality", "step", "PSNR (dB)", panels=2)
    right.set_ylabel("SSIM")
    for run in runs:
        for ax, key, final in ((left, "test_psnr", "psnr"), (right, "test_ssim", "ssim")):
            steps, values = run.series(key)
            if run.metrics.get(final) is not None:
                steps = np.append(steps, run.metrics.get("steps", steps[-1] if steps.size else 0))
                values = np.append(values, run.metrics[final])
            label = run.name
            if ax is left and run.metrics.get("lpips") is not None:
                label += f" (LPIPS-{run.metrics.get('lpips_net', '')} {run.metrics['lpips']:.3f})"
            if steps.size:
                line, = ax.plot(steps, values, marker=".", label=label)
                ax.plot(steps[-1:], values[-1:], marker="*", markersize=12, color=line.get_color())
    _legend(left)
    return _png(figure)


def _series(runs: list[RunRecord], key: str, title: str, ylabel: str) -> bytes:
    figure, (ax,) = _axes(title, "step", ylabel)
    for run in runs:
        steps, values = run.series(key)
        ax.plot(steps, values, label=run.name)
    _legend(ax)
    return _png(figure)


def loss(runs: list[RunRecord]) -> bytes:
    return _series(runs, "loss", "Training loss (0.8 L1 + 0.2 D-SSIM + regularizers)", "loss")


def gaussians(runs: list[RunRecord]) -> bytes:
    return _series(runs, "num_gaussians", "Number of Gaussians", "Gaussians")


REFINE_KEYS = ("relocated", "added", "cloned", "split", "pruned")
# MCMC's health at its refine steps (strategy/health.py): shares on the left axis, copies per host on the right.
HEALTH_SHARES = {"dead_share": "dead", "unseen_dead_share": "dead no view reached",
                 "born_dead_share": "copies born dead"}
HEALTH_COPIES = {"copies_max": "copies per host, most", "copies_mean": "copies per host, mean"}


def refinement(runs: list[RunRecord]) -> bytes:
    """Relocated / added (MCMC) or cloned / split (ADC) and pruned Gaussians per log record (every 100 steps: one
    refine step at the paper's schedule); beside it, for MCMC, the health levels of the last refine step of each
    record: the share of the Gaussians dead, of those the share no view reached, of the copies the share born dead,
    and the copies per host."""
    health = any(run.series("dead_share")[1].size for run in runs)
    figure, axes = _axes("Refinement per 100 steps", "step", "Gaussians", panels=2 if health else 1)
    styles = {"relocated": "-", "added": "--", "cloned": "-", "split": "--", "pruned": ":"}
    for run in runs:
        for key in REFINE_KEYS:
            steps, values = run.series(key)
            if values.size and values.any():
                axes[0].plot(steps, values, styles[key], label=f"{run.name}: {key}" if len(runs) > 1 else key)
    _legend(axes[0])
    if health:
        shares, copies = axes[1], axes[1].twinx()
        shares.set_ylabel("share")
        shares.set_ylim(0, 1)
        copies.set_ylabel("copies per host")
        for run in runs:
            prefix = f"{run.name}: " if len(runs) > 1 else ""
            for key, label in HEALTH_SHARES.items():
                steps, values = run.series(key)
                if values.size:
                    shares.plot(steps, values, label=prefix + label)
            for key, label in HEALTH_COPIES.items():
                steps, values = run.series(key)
                if values.size:
                    copies.plot(steps, values, ":", label=prefix + label)
        shares.set_title("MCMC at its refine steps", fontsize=9)
        lines = shares.get_legend_handles_labels(), copies.get_legend_handles_labels()
        shares.legend(lines[0][0] + lines[1][0], lines[0][1] + lines[1][1], fontsize=7)
    return _png(figure)


def distributions(runs: list[RunRecord]) -> bytes:
    """Opacity and largest-scale histograms of the final Gaussians; the share of dead ones (opacity <= DEAD_OPACITY)
    is what a lower cap would save."""
    figure, (left, right) = _axes("Final Gaussians", "opacity", "Gaussians", panels=2)
    right.set_xlabel("largest scale (log10)")
    bins = np.linspace(0, 1, 51)
    for run in runs:
        label = f"{run.name}: {run.dead_fraction:.1%} dead (opacity <= {DEAD_OPACITY})"
        left.hist(run.opacities, bins=bins, histtype="step", label=label)
        right.hist(np.log10(np.maximum(run.max_scales, 1e-12)), bins=50, histtype="step", label=run.name)
    left.set_yscale("log")
    _legend(left)
    return _png(figure)


def step_time(runs: list[RunRecord]) -> bytes:
    figure, (ax,) = _axes("Training time per step", "step", "milliseconds per step")
    for run in runs:
        # A resumed run logs the steps after its checkpoint again: the later record of a step wins.
        latest = {r["step"]: r["elapsed_seconds"] for r in run.log if "loss" in r and "elapsed_seconds" in r}
        rows = sorted(latest.items())
        if len(rows) >= 2:
            steps, seconds = np.array(rows, dtype=float).T
            ax.plot(steps[1:], np.diff(seconds) / np.diff(steps) * 1000.0, marker=".", label=run.name)
        elif rows:
            ax.plot(rows[0][0], rows[0][1] / rows[0][0] * 1000.0, marker="o", label=run.name)
    _legend(ax)
    return _png(figure)


def view_grid(rows: list[tuple[str, float, np.ndarray, np.ndarray]]) -> bytes:
    """Rows of (view name, PSNR, render, ground truth) as uint8 images, in the given order."""
    return image_grid([[(f"{name}: render, {value:.2f} dB", rendered), ("ground truth", truth)]
                       for name, value, rendered, truth in rows])


def image_grid(rows: list[list[tuple[str, np.ndarray]]]) -> bytes:
    """Rows of (title, uint8 image) panels, in the given order."""
    columns = max(len(panels) for panels in rows)
    figure = Figure(figsize=(3.0 * columns, 2.8 * len(rows)))
    axes = figure.subplots(len(rows), columns, squeeze=False)
    for panels, row in zip(rows, axes):
        for (title, image), ax in zip(panels, row):
            ax.imshow(image)
            ax.set_title(title, fontsize=9)
        for ax in row:
            ax.set_axis_off()
    figure.tight_layout()
    return _png(figure)
