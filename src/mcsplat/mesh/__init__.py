"""Meshes from trained Gaussians: `extract(model, views)` fuses the median depth of every view, where its nearest
views confirm it (and its empty space in front of its clear depth), into a truncated signed distance volume and
returns its zero level set as a coloured trimesh.Trimesh; `write_mesh` writes it as .ply, .glb or .obj.
`mcsplat export RUN --format mesh` is the command (docs/outputs.md, "A mesh of the scene").

    grid.py         where the volume lies, its voxel size, whether it fits in memory
    consistency.py  which pixels' depths the nearest other views confirm
    clear_space.py  the depth in front of which a view vouches for empty space (where its ray's alpha is still low)
    fusion.py       the signed distance volume, the fusion of one view, the closing of narrow gaps
    marching_cubes.py  the volume's zero level set (scikit-image's marching cubes) and vertex colours
    clean.py        dropping small pieces
    pipeline.py     extract(): the pipeline
    options.py      MeshOptions: how a mesh is made (the export command's mesh options)
    files.py        mesh files
    raster.py       a depth-buffer rasterizer for pictures and checks of a mesh
"""

from __future__ import annotations

import importlib
from typing import Any

from .options import DEFAULT_VOXEL_BUDGET, MeshOptions

# The pipeline loads on first use (trimesh, scikit-image): the CLI imports options.py for its options, and
# `mcsplat --help` stays quick.
_LAZY = {"extract": ".pipeline", "write_mesh": ".files", "read_mesh": ".files", "holds_mesh": ".files",
         "check_mesh_path": ".files", "MESH_ENDINGS": ".files"}

__all__ = ["extract", "MeshOptions", "DEFAULT_VOXEL_BUDGET", "write_mesh", "read_mesh", "holds_mesh",
           "check_mesh_path", "MESH_ENDINGS"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = globals()[name] = getattr(importlib.import_module(_LAZY[name], __name__), name)
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
