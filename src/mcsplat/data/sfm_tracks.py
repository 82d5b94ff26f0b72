"""Which SfM points each image of a COLMAP model saw: its tracks, read back as the points of each view.

COLMAP's images.bin lists, for every image, its 2D keypoints with the id of the 3D point each one observes (or none);
points3D.bin lists the points by id. Together they say which points an image saw, which is what sparse depth
supervision needs (depth_supervision/terms.py): a point is held to the depth of the images that triangulated it,
not to every image it merely projects into (where something in front may hide it).

    points_seen(root) -> {view name: float64 [k, 3] world points}, or None for a scene that is not a COLMAP model

A view's name is its image's name without the file ending, as the COLMAP loader names it. Points with NaN or inf
coordinates are left out, as the loader leaves them out.
"""

from __future__ import annotations

import struct
from pathlib import Path, PurePosixPath

import numpy as np

from . import colmap, colmap_files
from ..errors import DataError

_OBSERVATION = np.dtype([("xy", "<f8", (2,)), ("point3D_id", "<i8")])  # images.bin's 2D points, packed: 24 bytes


def points_seen(root: Path) -> dict[str, np.ndarray] | None:
    """{view name: the world points [k, 3] its image observed}, for the COLMAP model under `root` (None when there
    is none). Images that saw no point are left out."""
    found = colmap.find_model(Path(root))
    if found is None:
        return None
    folder, ext = found
    if ext == "bin":
        observed = _observations_bin(folder / "images.bin")
        ids, xyz = _points_bin(folder / "points3D.bin")
    else:
        observed, ids, xyz = _read_text(folder)
    finite = np.isfinite(xyz).all(axis=1)
    ids, xyz = ids[finite], xyz[finite]
    order = np.argsort(ids)
    ids, xyz = ids[order], xyz[order]
    seen = {}
    for name, point_ids in observed.items():
        point_ids = np.unique(point_ids[point_ids >= 0])  # -1: a keypoint without a point (COLMAP's invalid id)
        where = np.clip(np.searchsorted(ids, point_ids), 0, max(len(ids) - 1, 0))
        known = (ids[where] == point_ids) if len(ids) else np.zeros(len(point_ids), dtype=bool)
        if known.any():
            seen[str(PurePosixPath(name).with_suffix(""))] = xyz[where[known]]
    return seen


def _observations_bin(path: Path) -> dict[str, np.ndarray]:
    """{image name: the point3D ids of its keypoints (-1: none)} from images.bin."""
    data = path.read_bytes()
    observed = {}
    try:
        (count,) = struct.unpack_from("<Q", data, 0)
        offset = 8
        for _ in range(count):
            end = data.index(b"\0", offset + 64)
            name = data[offset + 64:end].decode("utf-8", errors="replace")
            (points2d,) = struct.unpack_from("<Q", data, end + 1)
            offset = end + 9
            rows = np.frombuffer(data, dtype=_OBSERVATION, count=points2d, offset=offset)
            observed[name] = rows["point3D_id"].copy()
            offset += _OBSERVATION.itemsize * points2d
    except (struct.error, ValueError):
        raise DataError(f"{path} is truncated or corrupt; export the model again (colmap model_converter)") from None
    return observed


def _points_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(ids int64 [P], xyz float64 [P, 3]) of points3D.bin, in file order."""
    xyz, _, ids = colmap_files.read_points3d_bin(path, ids=True)
    return ids, xyz


def _read_text(folder: Path) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """The same from a text model, through pycolmap (text models are small)."""
    reconstruction, _, _ = colmap._read_reconstruction(folder, "txt")
    observed = {image.name: np.array([point.point3D_id if point.has_point3D() else -1 for point in image.points2D],
                                     dtype=np.int64)
                for image in reconstruction.images.values()}
    ids = np.array(sorted(reconstruction.points3D.keys()), dtype=np.int64)
    xyz = np.array([reconstruction.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    return observed, ids, xyz
