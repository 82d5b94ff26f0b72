"""The outputs a render gives only when a caller asks for them, each a registered pass run around the compositing:

    median_depth   the depth where the accumulated alpha reaches 0.5 (median.py; the compositing kernels find the
                   Gaussian, so the pass asks them to)
    normals        the normal map, each Gaussian's normal composited like the colour (normals.py) ...
    planar_depth   ... and, in the same pass, the depth of the composited planes
    distortion     2DGS's depth distortion (distortion.py), a compositing pass of its own

`render(..., outputs={"normals"})` runs the passes that give what is asked and nothing else, so that a render without
them costs nothing more. Loss terms name the outputs they read (loss_terms.render_outputs). A new output is a
function here and its entry in PASSES, with its field in RenderResult.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Collection

import torch

from ...camera import Camera
from .distortion import distortion_from_sums, inverse_depths
from .median import median_depth
from .normals import depth_from_planes, gaussian_normals, plane_distances

Composited = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class PassInputs:
    """What a pass is handed: the Gaussians (activated), the camera, and the compositing of the render."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor  # as composited (the anti-aliasing's compensation applied)
    camera: Camera
    near: float
    # (sum w_i values_i [H, W, 3], alpha, sum w_i scalars_i) with the colour's weights, over zero
    composited: Composited
    median_ids: torch.Tensor | None  # [H, W] the Gaussian at which alpha reaches 0.5, when a pass asked for it


@dataclass(frozen=True)
class OutputPass:
    gives: frozenset[str]  # the outputs it gives (render's `outputs` names, RenderResult's fields)
    run: Callable[[PassInputs, frozenset[str]], dict[str, torch.Tensor]]  # the asked outputs it gives, by field
    needs_median_ids: bool = False  # the compositing must find each pixel's median Gaussian


def _median(inputs: PassInputs, asked: frozenset[str]) -> dict[str, torch.Tensor]:
    return {"median_depth": median_depth(inputs.median_ids, inputs.means, inputs.quats, inputs.scales, inputs.camera)}


def _planes(inputs: PassInputs, asked: frozenset[str]) -> dict[str, torch.Tensor]:
    each = gaussian_normals(inputs.means, inputs.quats, inputs.scales, inputs.camera)
    planar = "planar_depth" in asked
    distances = plane_distances(each, inputs.means, inputs.camera) if planar else torch.zeros_like(inputs.opacities)
    normal, _, distance_map = inputs.composited(each, distances)
    found = {"normal": normal} if "normals" in asked else {}
    if planar:
        found["planar_depth"] = depth_from_planes(normal, distance_map, inputs.camera)
    return found


def _distortion(inputs: PassInputs, asked: frozenset[str]) -> dict[str, torch.Tensor]:
    inverse = inverse_depths(inputs.means, inputs.camera, inputs.near)
    sums, weight, _ = inputs.composited(torch.stack([inverse, inverse * inverse, torch.zeros_like(inverse)], dim=-1),
                                        torch.zeros_like(inverse))
    return {"distortion": distortion_from_sums(weight, sums[..., 0], sums[..., 1])}


PASSES = (OutputPass(frozenset({"median_depth"}), _median, needs_median_ids=True),
          OutputPass(frozenset({"normals", "planar_depth"}), _planes),
          OutputPass(frozenset({"distortion"}), _distortion))
OUTPUTS = frozenset().union(*(p.gives for p in PASSES))


def passes_for(outputs: Collection[str]) -> list[OutputPass]:
    """The passes that give `outputs`, in PASSES' order; a name no pass gives is a ValueError."""
    asked = frozenset(outputs)
    unknown = asked - OUTPUTS
    if unknown:
        raise ValueError(f"render: no output {', '.join(sorted(unknown))}; the outputs given on request are "
                         f"{', '.join(sorted(OUTPUTS))}")
    return [output_pass for output_pass in PASSES if output_pass.gives & asked]
