"""Checks of COLMAP model files, and a reader for points3D.

pycolmap reads a well-formed model, but on a truncated or corrupt .bin file it can loop forever or try to allocate
tens of GB. So every .bin file is walked here first (cheap: only counts, ids and lengths are read) and must end exactly
where its structure says, before pycolmap sees it. For text models pycolmap fails cleanly; `diagnose_text_model`
then finds which file and line is wrong so that the message can name it.

Binary layout (little endian), as written by COLMAP:
  cameras.bin   u64 n; n x (i32 id, i32 model, u64 width, u64 height, f64 params[count(model)])
  images.bin    u64 n; n x (u32 id, f64 qvec[4], f64 tvec[3], u32 camera_id, name bytes + NUL, u64 m,
                            m x (f64 x, f64 y, i64 point3D_id))
  points3D.bin  u64 n; n x (u64 id, f64 xyz[3], u8 rgb[3], f64 error, u64 t, t x (i32 image_id, i32 point2D_idx))
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import DataError

# COLMAP camera models: id -> (name, number of parameters).
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
MODEL_PARAMS_BY_NAME = {name: count for name, count in CAMERA_MODELS.values()}

_POINT_HEADER = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"),
                          ("track_length", "<u8")])  # packed: 51 bytes
_XYZ_RGB = np.dtype([("xyz", "<f8", (3,)), ("rgb", "u1", (3,))])  # bytes 8..35 of a point, packed
_CORRUPT_HINT = "the file is truncated or corrupt; export the model again (colmap model_converter)"


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc.strerror or exc}") from None


def _count(data: bytes, path: Path, min_record: int, what: str) -> int:
    if len(data) < 8:
        raise DataError(f"{path} is {len(data)} bytes long, too short to hold the number of {what}; {_CORRUPT_HINT}")
    (count,) = struct.unpack_from("<Q", data, 0)
    if count * min_record > len(data) - 8:
        raise DataError(f"{path} says it holds {count} {what} but is only {len(data)} bytes long; {_CORRUPT_HINT}")
    return count


def check_cameras_bin(path: Path) -> set[int]:
    """Walk cameras.bin; returns the camera ids. DataError if the structure does not fit the file."""
    data = _read(path)
    count = _count(data, path, 24 + 8 * 2, "cameras")
    offset, ids = 8, set()
    for index in range(count):
        if offset + 24 > len(data):
            raise DataError(f"{path} ends inside camera {index + 1} of {count}; {_CORRUPT_HINT}")
        camera_id, model, width, height = struct.unpack_from("<iiQQ", data, offset)
        if model not in CAMERA_MODELS:
            raise DataError(f"{path}: camera {camera_id} has unknown camera model id {model}; {_CORRUPT_HINT}")
        if not (0 < width < 2**20 and 0 < height < 2**20):
            raise DataError(f"{path}: camera {camera_id} has an impossible size {width}x{height}; {_CORRUPT_HINT}")
        offset += 24 + 8 * CAMERA_MODELS[model][1]
        if offset > len(data):
            raise DataError(f"{path} ends inside camera {index + 1} of {count}; {_CORRUPT_HINT}")
        ids.add(camera_id)
    if offset != len(data):
        raise DataError(f"{path} has {len(data) - offset} unexpected bytes after its {count} cameras; {_CORRUPT_HINT}")
    return ids


def check_images_bin(path: Path, camera_ids: set[int]) -> int:
    """Walk images.bin; returns the number of images. Also checks that each image's camera exists."""
    data = _read(path)
    count = _count(data, path, 4 + 56 + 4 + 1 + 8, "images")
    offset = 8
    for index in range(count):
        if offset + 64 > len(data):
            raise DataError(f"{path} ends inside image {index + 1} of {count}; {_CORRUPT_HINT}")
        image_id = struct.unpack_from("<I", data, offset)[0]
        camera_id = struct.unpack_from("<I", data, offset + 60)[0]
        end = data.find(b"\0", offset + 64, offset + 64 + 4096)
        if end < 0:
            raise DataError(f"{path}: the name of image {image_id} is not terminated; {_CORRUPT_HINT}")
        if camera_id not in camera_ids:
            raise DataError(f"{path}: image {image_id} uses camera {camera_id}, which is not in cameras.bin; "
                            f"{_CORRUPT_HINT}")
        offset = end + 1
        if offset + 8 > len(data):
            raise DataError(f"{path} ends inside image {index + 1} of {count}; {_CORRUPT_HINT}")
        (points2d,) = struct.unpack_from("<Q", data, offset)
        offset += 8 + 24 * points2d
        if offset > len(data):
            raise DataError(f"{path} ends inside image {index + 1} of {count}; {_CORRUPT_HINT}")
    if offset != len(data):
        raise DataError(f"{path} has {len(data) - offset} unexpected bytes after its {count} images; {_CORRUPT_HINT}")
    return count


def _point_offsets(data: bytes, path: Path) -> np.ndarray:
    """Where each point of points3D.bin's bytes starts, the file walked to its end."""
    count = _count(data, path, _POINT_HEADER.itemsize, "points")
    offsets = np.empty(count, dtype=np.int64)
    offset, size, header = 8, len(data), _POINT_HEADER.itemsize
    for index in range(count):
        if offset + header > size:
            raise DataError(f"{path} ends inside point {index + 1} of {count}; {_CORRUPT_HINT}")
        offsets[index] = offset
        offset += header + 8 * int.from_bytes(data[offset + 43:offset + 51], "little")
    if offset != size:
        where = "ends inside the last points" if offset > size else f"has {size - offset} unexpected bytes at the end"
        raise DataError(f"{path} {where}; {_CORRUPT_HINT}")
    return offsets


def read_points3d_bin(path: Path, ids: bool = False):
    """Walk and read points3D.bin: xyz float64 [P, 3] and rgb uint8 [P, 3], in file order; with `ids`, also the
    points' ids, int64 [P] (what the images' tracks name them by), after them."""
    data = _read(path)
    offsets = _point_offsets(data, path)
    count = len(offsets)
    # Gather the 27 bytes of xyz + rgb of each point (and its 8-byte id), in chunks so the index array stays small.
    raw, columns, id_columns = np.frombuffer(data, dtype=np.uint8), np.arange(8, 35), np.arange(8)
    xyz, rgb = np.empty((count, 3), dtype=np.float64), np.empty((count, 3), dtype=np.uint8)
    point_ids = np.empty(count, dtype=np.int64)
    for start in range(0, count, 65536):
        chunk = raw[offsets[start:start + 65536, None] + columns].reshape(-1).view(_XYZ_RGB)
        xyz[start:start + len(chunk)] = chunk["xyz"]
        rgb[start:start + len(chunk)] = chunk["rgb"]
        if ids:
            point_ids[start:start + len(chunk)] = raw[offsets[start:start + 65536, None] + id_columns].reshape(-1) \
                .view("<u8").astype(np.int64)
    return (xyz, rgb, point_ids) if ids else (xyz, rgb)


def read_points3d_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """points3D.txt: one point per line, `ID X Y Z R G B ERROR TRACK...`."""
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc.strerror or exc}") from None
    xyz, rgb = [], []
    for number, line in enumerate(lines, start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        try:
            if len(tokens) < 8:
                raise ValueError
            xyz.append([float(t) for t in tokens[1:4]])
            rgb.append([int(t) for t in tokens[4:7]])
        except ValueError:
            raise DataError(f"{path} line {number} is not a point 'ID X Y Z R G B ERROR TRACK[]'; {_CORRUPT_HINT}")\
                from None
    return (np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
            np.clip(np.asarray(rgb, dtype=np.int64), 0, 255).astype(np.uint8).reshape(-1, 3))


def _data_lines(path: Path) -> list[tuple[int, str]]:
    text = path.read_text(encoding="utf-8", errors="replace")
    return [(n, line) for n, line in enumerate(text.splitlines(), start=1) if not line.startswith("#")]


def diagnose_text_model(model_dir: Path) -> str | None:
    """After pycolmap failed on a text model: the first problem found, naming the file and line, or None."""
    cameras, images, points = (model_dir / f"{name}.txt" for name in ("cameras", "images", "points3D"))
    camera_ids: set[int] = set()
    for number, line in _data_lines(cameras):
        tokens = line.split()
        if not tokens:
            continue
        problem = None
        if len(tokens) < 4 or tokens[1] not in MODEL_PARAMS_BY_NAME:
            problem = "is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]' with a known COLMAP model"
        elif len(tokens) != 4 + MODEL_PARAMS_BY_NAME[tokens[1]]:
            problem = f"has {len(tokens) - 4} parameters, the {tokens[1]} model needs {MODEL_PARAMS_BY_NAME[tokens[1]]}"
        else:
            try:
                camera_ids.add(int(tokens[0]))
                if int(tokens[2]) <= 0 or int(tokens[3]) <= 0:
                    problem = "has a width or height that is not positive"
                [float(t) for t in tokens[4:]]
            except ValueError:
                problem = "holds something that is not a number"
        if problem:
            return f"{cameras} line {number} {problem}"
    lines = _data_lines(images)
    index = 0
    while index < len(lines):
        number, line = lines[index]
        tokens = line.split()
        if not tokens:
            index += 1
            continue
        try:
            if len(tokens) < 10:
                raise ValueError
            [float(t) for t in tokens[1:8]]
            camera_id = int(tokens[8])
        except ValueError:
            return f"{images} line {number} is not 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'"
        if camera_id not in camera_ids:
            return f"{images} line {number}: camera {camera_id} is not in {cameras.name}"
        if index + 1 >= len(lines):
            return f"{images} ends after line {number}: the line of 2D points of image {tokens[0]} is missing"
        number2, line2 = lines[index + 1]
        tokens2 = line2.split()
        try:
            if len(tokens2) % 3:
                raise ValueError
            [float(t) for t in tokens2]
        except ValueError:
            return f"{images} line {number2} is not a list of 2D points 'X Y POINT3D_ID ...'"
        index += 2
    for number, line in _data_lines(points):
        tokens = line.split()
        if not tokens:
            continue
        try:
            if len(tokens) < 8 or (len(tokens) - 8) % 2:
                raise ValueError
            [float(t) for t in tokens]
        except ValueError:
            return f"{points} line {number} is not 'POINT3D_ID X Y Z R G B ERROR TRACK[]'"
    return None
