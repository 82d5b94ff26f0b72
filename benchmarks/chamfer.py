"""Chamfer distance between a mesh and the true surface it should be (exact_mesh_scene.py's mesh.ply), for the
benchmarks; not part of the package.

    accuracy      points sampled uniformly (by area) on the exported surface -> their distance to the true surface:
                  what the mesh shows that is not there (floaters, a swollen or shifted surface)
    completeness  points sampled likewise on the true surface -> their distance to the exported one: what of the
                  truth the mesh misses (holes, unseen parts)
    Chamfer       the mean of the two
    offset        the median signed distance of the accuracy's points, negative inside the true shape: whether the
                  exported surface sits inside or outside the truth (its sign is that of the true surface's normal at
                  the nearest of the completeness's points, so the true mesh must face outwards)

each as a median and a mean, in scene units and in % of the true mesh's bounding-box diagonal (so that figures of
shapes of other sizes compare), and the share within THRESHOLD of the diagonal (precision for accuracy, recall for
completeness) with their harmonic mean, the F-score of Tanks and Temples. The distances are to the surface, not to
the other side's samples: point to triangle, exactly, by mesh_quality.distance_to_mesh (the nearest of the triangles
whose centroids are nearest, exact for meshes of small even triangles such as marching cubes makes).
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from mesh_quality import distance_to_mesh

SAMPLES = 200_000   # points sampled on each surface
THRESHOLD = 0.01    # "within": this share of the true mesh's bounding-box diagonal


def diagonal(mesh: trimesh.Trimesh) -> float:
    """Length of the mesh's axis-aligned bounding box's diagonal: the unit the figures are given in."""
    low, high = np.asarray(mesh.vertices).min(axis=0), np.asarray(mesh.vertices).max(axis=0)
    return float(np.linalg.norm(high - low))


def surface_samples(mesh: trimesh.Trimesh, count: int, seed: int) -> np.ndarray:
    """[count, 3] points uniform on the surface (triangles drawn by area): a mesh of many small triangles in one
    place weighs no more than its area, as vertices would."""
    return oriented_samples(mesh, count, seed)[0]


def oriented_samples(mesh: trimesh.Trimesh, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """surface_samples and the unit normal [count, 3] of the triangle each lies on."""
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise ValueError("the mesh has no surface to sample (no faces, or all of zero area)")
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals)[faces]


def to_surface(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """[P] distance from each point to the nearest point of `mesh`'s surface."""
    return distance_to_mesh(points, np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))


def signs(points: np.ndarray, samples: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[P] +1 where a point lies on the outer side of the surface that `samples` with their `normals` cover (by the
    nearest sample), else -1."""
    _, nearest = cKDTree(samples).query(points)
    return np.where(np.einsum("ij,ij->i", points - samples[nearest], normals[nearest]) > 0, 1.0, -1.0)


def summary(distances: np.ndarray, unit: float, threshold: float) -> dict:
    """Median and mean, also in % of `unit`, and the share within `threshold` x `unit`."""
    median, mean = float(np.median(distances)), float(distances.mean())
    return {"median": median, "mean": mean, "median_pct": 100 * median / unit, "mean_pct": 100 * mean / unit,
            "within": float((distances <= threshold * unit).mean())}


def chamfer(exported: trimesh.Trimesh, true: trimesh.Trimesh, samples: int = SAMPLES, seed: int = 0,
            threshold: float = THRESHOLD) -> dict:
    """The figures of the module docstring, flat: accuracy_*, completeness_*, chamfer_* (median, mean, and both in %
    of the true diagonal), accuracy_within, completeness_within and f_score (shares in [0, 1]), diagonal."""
    unit = diagonal(true)
    shown = surface_samples(exported, samples, seed)
    truth, normals = oriented_samples(true, samples, seed + 1)
    off = to_surface(shown, true)
    accuracy = summary(off, unit, threshold)
    completeness = summary(to_surface(truth, exported), unit, threshold)
    offset = float(np.median(off * signs(shown, truth, normals)))
    record = {"diagonal": unit, "threshold": threshold, "samples": samples, "offset_median": offset,
              "offset_median_pct": 100 * offset / unit}
    for name, figures in (("accuracy", accuracy), ("completeness", completeness)):
        record.update({f"{name}_{key}": value for key, value in figures.items()})
    for key in ("median", "mean", "median_pct", "mean_pct"):
        record[f"chamfer_{key}"] = (accuracy[key] + completeness[key]) / 2
    precision, recall = accuracy["within"], completeness["within"]
    record["f_score"] = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return record
