"""The test views of a saved run and a function that renders one, for the report's grid of worst views and its
picture of the mesh, when a command (`mcsplat report`, `mcsplat export --format mesh`) makes the report rather than
the training run (which hands ReportWriter its own)."""

from __future__ import annotations

import warnings
from pathlib import Path

import torch

from ..compute.device import resolve_device
from ..data.images import uint8_pixels
from ..errors import MCSplatError
from ..render import render
from ..run.trained import load


def saved_run_views(path: Path, device_name: str):
    """The run's test views and a function rendering one, for the report's grid (none when the scene is gone)."""
    run = load(path, resolve_device(device_name))
    try:
        scene, background = run.scene, run.background
    except MCSplatError as error:
        warnings.warn(f"the report has no test-view grid: the scene cannot be loaded ({error})")
        return (), None

    @torch.no_grad()
    def render_view(view):
        return uint8_pixels(render(run.model, view.camera.to(run.device), background, run.sh_degree).rgb)

    return scene.test, render_view
