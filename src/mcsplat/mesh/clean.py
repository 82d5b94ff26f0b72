"""Dropping the small islands of a mesh: the floaters a few stray Gaussians leave in the fused volume."""

from __future__ import annotations

import numpy as np
import trimesh


def drop_small_pieces(mesh: trimesh.Trimesh, min_share: float) -> trimesh.Trimesh:
    """The mesh without its connected pieces (faces joined by shared edges) of fewer faces than `min_share` times
    the largest piece's; 0 keeps every piece."""
    if min_share <= 0 or len(mesh.faces) == 0:
        return mesh
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    sizes = np.bincount(labels)
    keep = sizes[labels] >= min_share * sizes.max()
    if keep.all():
        return mesh
    kept = mesh.copy()
    kept.update_faces(keep)
    kept.remove_unreferenced_vertices()
    return kept
