"""Which Gaussians a Gaussian format holds: those the training views show (--prune), within --max-scale and
--max-distance, above --min-opacity, at most --max-gaussians; each step says what it left out, and with --prune or a
limit the test views are scored with and without the rest.

The run's heavy modules load inside the functions: the CLI imports this package for --format's choices, and
`mcsplat --help` stays quick.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import MCSplatError
from ..gaussians import DEAD_OPACITY
from ..io.formats import outliers, select_gaussians

if TYPE_CHECKING:
    from ..run.trained import TrainedRun

Params = dict[str, np.ndarray]


@dataclass(frozen=True)
class SelectionOptions:
    """Which Gaussians a Gaussian format holds (every format but the mesh)."""

    min_opacity: float = DEAD_OPACITY
    """Leave out Gaussians of this opacity or less (0.005: the dead ones MCMC relocates)."""
    max_gaussians: int | None = None
    """Keep at most N: those that contribute most (opacity x largest cross-section)."""
    prune: bool = False
    """Also leave out the Gaussians composited into no pixel of any training view (needs the run's scene), and
    print the test PSNR with and without them."""
    max_scale: float | None = None
    """Leave out Gaussians whose largest axis exceeds this many scene radii (the training cameras' extent): viewers
    draw very large splats badly. Prints the test PSNR with and without them."""
    max_distance: float | None = None
    """Leave out Gaussians farther than this many scene radii from the training cameras' centre: very far splats
    leave viewers that sort by depth too little precision for the scene. Prints the test PSNR with and without."""


def chosen_gaussians(run: TrainedRun, params: Params, options: SelectionOptions) -> np.ndarray:
    """Indices (ascending) of the Gaussians to write, of `params` (the run's model as numpy arrays)."""
    limits = options.max_scale is not None or options.max_distance is not None
    extent = _extent(run, required=limits)
    candidates = np.arange(run.model.num_gaussians)
    if options.prune:
        candidates = np.flatnonzero(_seen(run).cpu().numpy())
    if limits:
        inside = outliers.within(params, extent, options.max_scale, options.max_distance)[candidates]
        print(f"{int((~inside).sum()):,} Gaussians beyond --max-scale / --max-distance: left out")
        candidates = candidates[inside]
    chosen = candidates[select_gaussians({k: v[candidates] for k, v in params.items()}, options.min_opacity,
                                         options.max_gaussians)]
    if chosen.size == 0:
        raise MCSplatError(f"no Gaussian has opacity above --min-opacity {options.min_opacity}"
                           f"{' and shows in a training view (--prune)' if options.prune else ''}"
                           f"{' within --max-scale / --max-distance' if limits else ''}; lower it")
    if extent is not None:
        print(outliers.describe({k: v[chosen] for k, v in params.items()}, extent))
    if options.prune or limits:
        _compare_on_test_views(run, chosen)
    return chosen


def _extent(run: TrainedRun, required: bool) -> outliers.Extent | None:
    """The training cameras' centre and radius, for the very large and very far Gaussians; None (said) when the
    run's scene cannot be loaded and no limit needs it."""
    try:
        scene = run.scene
    except MCSplatError as error:
        if required:
            raise MCSplatError(f"--max-scale / --max-distance need the run's scene: {error}") from None
        print(f"not checked for very large or very far Gaussians: {error}")
        return None
    return outliers.Extent(centre=scene.centre.numpy(), radius=float(scene.radius))


def _seen(run: TrainedRun) -> torch.Tensor:
    """Which Gaussians the run's training views show (printing how many show nowhere)."""
    from ..visibility import count_invisible, describe, seen_in

    seen = seen_in(run.model, run.scene.train, run.background, run.device, progress=True)
    print(f"{describe(count_invisible(run.model, seen).as_dict())}: left out")
    return seen


def _compare_on_test_views(run: TrainedRun, chosen: np.ndarray) -> None:
    """The test PSNR with every Gaussian and with the `chosen` only: what leaving the others out costs."""
    from ..run.evaluation import evaluate

    keep = torch.zeros(run.model.num_gaussians, dtype=torch.bool)
    keep[torch.from_numpy(chosen)] = True
    keep = keep.to(run.device)
    test = run.scene.test
    full = evaluate(run.model, test, run.background, run.sh_degree, run.device, progress=True).psnr
    kept = evaluate(run.model.subset(keep), test, run.background, run.sh_degree, run.device, progress=True).psnr
    print(f"test PSNR on {len(test)} views: {full:.3f} dB with every Gaussian, {kept:.3f} dB with the "
          f"{int(keep.sum()):,} exported ({kept - full:+.3f} dB)")
