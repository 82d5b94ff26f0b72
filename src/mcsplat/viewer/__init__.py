"""The live web viewer (optional extra: `pip install mcsplat[viewer]`, which brings viser).

The browser shows images rendered by our own rasterizer (full SH, exactly what training optimises) from the camera
the user drives, at lower resolution while the camera moves; the training views appear as frustums; a panel shows
step, loss, PSNR, Gaussians and speed, with pause / resume and the render mode (RGB, depth, alpha, centres) and SH
degree. TrainingViewer is a subscriber of the training run (run/events.py); `view_saved` shows a finished run or .ply.
The server listens on 127.0.0.1 unless asked otherwise.
"""

from __future__ import annotations

import importlib.util

from ..errors import MCSplatError

INSTALL_HINT = "pip install 'mcsplat[viewer]' (or: pip install viser==1.1.1)"


def require_viser() -> None:
    if importlib.util.find_spec("viser") is None:
        raise MCSplatError(f"the live viewer needs the optional package viser, which is not installed: {INSTALL_HINT}")


def __getattr__(name: str):
    # viser is imported only when a viewer is actually made.
    if name == "TrainingViewer":
        from .training import TrainingViewer
        return TrainingViewer
    if name == "view_saved":
        from .saved import view_saved
        return view_saved
    raise AttributeError(name)
