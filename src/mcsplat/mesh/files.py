"""Mesh files: a binary .ply with vertex colours, a .glb or an .obj, chosen by the file's ending; written atomically.
Also whether a file holds a mesh (a .ply may hold a mesh or 3DGS's Gaussians), for `mcsplat view`."""

from __future__ import annotations

from pathlib import Path

import trimesh

from ..errors import MCSplatError
from ..io.atomic import atomic_path
from ..io.formats.gltf import holds_gaussians

MESH_ENDINGS = (".ply", ".glb", ".obj")


def check_mesh_path(path: Path) -> None:
    """A one-line error unless `path` ends in a mesh format's ending."""
    if path.suffix.lower() not in MESH_ENDINGS:
        raise MCSplatError(f"--out {path}: a mesh is written as {', '.join(MESH_ENDINGS)} (by the file's ending); "
                           f"choose one of them")


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> None:
    """Write `mesh` as the format of `path`'s ending, atomically."""
    path = Path(path)
    check_mesh_path(path)
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lower()[1:])


def read_mesh(path: Path) -> trimesh.Trimesh:
    """A mesh file as one Trimesh (a .glb's scene is merged into one)."""
    try:
        loaded = trimesh.load(Path(path), force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds for a damaged file
        raise MCSplatError(f"{path}: not a mesh file trimesh can read ({error})") from None
    if len(loaded.faces) == 0:
        raise MCSplatError(f"{path}: the file holds no faces")
    return loaded


def holds_mesh(path: Path) -> bool:
    """A .glb (unless it holds Gaussians: KHR_gaussian_splatting) or .obj, or a .ply whose header declares faces
    (3DGS's .ply has vertices only)."""
    ending = Path(path).suffix.lower()
    if ending in (".glb", ".obj"):
        return ending == ".obj" or not holds_gaussians(Path(path))
    if ending != ".ply":
        return False
    with open(path, "rb") as file:
        for _ in range(200):  # a header is short; a file that never ends its header is no mesh of ours
            line = file.readline()
            if not line or line.strip() == b"end_header":
                return False
            words = line.split()
            if words[:2] == [b"element", b"face"] and len(words) == 3 and int(words[2]) > 0:
                return True
    return False
