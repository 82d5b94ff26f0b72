"""The report's picture of RUN/mesh.ply (written by `mcsplat export --format mesh`): from a few test views, the
splats beside the mesh in its vertex colours and the mesh shaded in grey, drawn by mesh/raster.py."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from ..mesh import read_mesh
from ..mesh.raster import picture
from ..run.folder import RunDir

MESH_VIEWS = 3
LONGEST_SIDE = 480  # pixels of a mesh picture's longest side


def mesh_figure_rows(run_path: Path, views: Sequence, render_view: Callable[[object], np.ndarray] | None
                     ) -> tuple[str, list[list[tuple[str, np.ndarray]]]]:
    """(caption, rows of (title, image) panels), or ("", []) when the run has no mesh or no views to see it from."""
    mesh_file = RunDir(run_path).mesh_file
    if not mesh_file.is_file() or not views:
        return "", []
    mesh = read_mesh(mesh_file)
    vertices = torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float32))
    faces = torch.from_numpy(np.asarray(mesh.faces, dtype=np.int64))
    colors = torch.from_numpy(np.asarray(mesh.visual.vertex_colors)[:, :3].copy())
    rows = []
    for view in list(views)[:: max(1, len(views) // MESH_VIEWS)][:MESH_VIEWS]:
        camera = view.camera
        shrink = min(1.0, LONGEST_SIDE / max(camera.width, camera.height))
        small = camera.scaled(max(1, round(camera.width * shrink)), max(1, round(camera.height * shrink)))
        name = Path(view.name).stem
        panels = [(f"{name}: splats", render_view(view))] if render_view is not None else []
        panels += [("mesh, vertex colours", picture(vertices, faces, small, colors)),
                   ("mesh, shaded", picture(vertices, faces, small))]
        rows.append(panels)
    caption = (f"The mesh of {mesh_file.name} ({len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces) from test "
               f"views: the splats, the mesh in its vertex colours, the mesh lit from the camera")
    return caption, rows
