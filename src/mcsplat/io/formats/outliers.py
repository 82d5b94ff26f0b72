"""Gaussians that other viewers draw badly: the very large and the very far.

MCMC's relocation and position noise leave some Gaussians far outside the captured region (a real capture's sky and
distant walls: on the cup capture one lies 4,800 scene radii from the cameras) and a few larger than the scene. A
viewer that sorts splats by depth in a fixed number of bits (SuperSplat's bin sort) spreads those bits over the whole
depth range, leaving too few for the scene itself (SuperSplat issue 396); and a splat larger than the scene is drawn
around the projection of its centre, visibly wrong up close (gsplat issue 785). `mcsplat export` reports them, and
--max-scale / --max-distance leave them out. Both are in scene radii: the training cameras' extent (scene.py's
`camera_radius`), measured from the mean of their centres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...errors import MCSplatError

REPORT_SCALE = 1.0       # reported: a largest axis of a scene radius or more ...
REPORT_DISTANCE = 100.0  # ... or a centre a hundred scene radii or more from the cameras' centre


@dataclass(frozen=True)
class Extent:
    """Where the training cameras are: the mean of their centres, and the scene radius around it."""

    centre: np.ndarray
    radius: float


def largest_axes(params: dict[str, np.ndarray], extent: Extent) -> np.ndarray:
    """[N] each Gaussian's largest scale, in scene radii."""
    return np.exp(params["log_scales"].astype(np.float64)).max(axis=1) / extent.radius


def distances(params: dict[str, np.ndarray], extent: Extent) -> np.ndarray:
    """[N] each Gaussian's distance from the cameras' centre, in scene radii."""
    return np.linalg.norm(params["means"].astype(np.float64) - extent.centre, axis=1) / extent.radius


def within(params: dict[str, np.ndarray], extent: Extent, max_scale: float | None = None,
           max_distance: float | None = None) -> np.ndarray:
    """[N] bool: no larger than `max_scale` and no farther than `max_distance` (scene radii; None: no limit)."""
    for option, value in (("--max-scale", max_scale), ("--max-distance", max_distance)):
        if value is not None and not (value > 0 and math.isfinite(value)):
            raise MCSplatError(f"{option} {value}: must be a positive number of scene radii")
    keep = np.ones(params["means"].shape[0], dtype=bool)
    if max_scale is not None:
        keep &= largest_axes(params, extent) <= max_scale
    if max_distance is not None:
        keep &= distances(params, extent) <= max_distance
    return keep


def describe(params: dict[str, np.ndarray], extent: Extent) -> str:
    """One line on the Gaussians beyond REPORT_SCALE or REPORT_DISTANCE among `params`, with the extremes."""
    if params["means"].shape[0] == 0:
        return "no Gaussians to check for very large or very far ones"
    axes, away = largest_axes(params, extent), distances(params, extent)
    big, far = int((axes >= REPORT_SCALE).sum()), int((away >= REPORT_DISTANCE).sum())
    extremes = f"largest {axes.max():.3g} scene radii across, farthest {away.max():,.3g} away"
    if big == 0 and far == 0:
        return f"no Gaussian larger than {REPORT_SCALE:g} scene radius or farther than {REPORT_DISTANCE:g} ({extremes})"
    return (f"{big:,} Gaussians larger than {REPORT_SCALE:g} scene radius and {far:,} farther than "
            f"{REPORT_DISTANCE:g} scene radii from the cameras ({extremes}): viewers that sort by depth in few bits "
            f"may draw the scene badly; --max-scale / --max-distance (in scene radii) leave them out")
