"""Meshes from trained Gaussians: `extract(model, views)` fuses the median depth of every view, where its nearest
views confirm it, into a truncated signed distance volume and returns its zero level set as a coloured
trimesh.Trimesh; `write_mesh` writes it as .ply, .glb or .obj. `mcsplat export RUN --format mesh` is the command
(docs/outputs.md, "A mesh of the scene").

    grid.py         where the volume lies, its voxel size, whether it fits in memory
    consistency.py  which pixels' depths the nearest other views confirm
    fusion.py       the signed distance volume, the fusion of one view, the closing of narrow gaps
    surface.py      marching cubes (scikit-image) and vertex colours
    clean.py        dropping small pieces
    extract.py      the pipeline
    files.py        mesh files
    raster.py       a depth-buffer rasterizer for pictures and checks of a mesh
"""

from .extract import DEFAULT_VOXEL_BUDGET, MeshOptions, extract
from .files import MESH_ENDINGS, check_mesh_path, holds_mesh, read_mesh, write_mesh

__all__ = ["extract", "MeshOptions", "DEFAULT_VOXEL_BUDGET", "write_mesh", "read_mesh", "holds_mesh",
           "check_mesh_path", "MESH_ENDINGS"]
