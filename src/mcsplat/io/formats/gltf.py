"""glTF 2.0 with Khronos's `KHR_gaussian_splatting` extension: a binary `.glb`, or a `.gltf` (JSON) with its `.bin`.

Sources of each convention (the extension's text is not vendored here; these are the readers that implement it):
- three.js r187 `examples/jsm/loaders/GLTFGaussianSplatLoaderExtension.js` (npm `three@0.187.0`): one mesh
  primitive per scene of Gaussians, `mode` 0 (POINTS), its `extensions.KHR_gaussian_splatting` object with
  `kernel: "ellipse"` (required), `colorSpace` (required), `projection: "perspective"` and
  `sortingMethod: "cameraDistance"`; the attributes POSITION, `KHR_gaussian_splatting:SCALE`, `:ROTATION`,
  `:OPACITY`, `:SH_DEGREE_0_COEF_0` (required) and `:SH_DEGREE_<l>_COEF_<m>` for l = 1..3, m = 0..2l (every
  coefficient of a degree, degrees contiguous).
- Values, from how that loader uses them (`utils/GaussianSplatUtils.js`): SCALE is the linear standard deviation per
  axis (exp of our log-scales; it composes the covariance from it as it is); ROTATION is a unit quaternion in glTF's
  order x, y, z, w; OPACITY is alpha in [0, 1] (sigmoid of our logits); SH_DEGREE_0_COEF_0 is the SH DC coefficient
  (colour = 0.5 + 0.28209479 * coefficient) and the higher ones the 3DGS rest coefficients, m = -l..l in order, per
  colour channel r, g, b (VEC3). All are float32 here (no quantisation: the compressed variant is
  `KHR_gaussian_splatting_compression_spz_2`, a draft, not written).
- colorSpace "srgb_rec709_display": the colours are the display sRGB the scene was trained to reproduce, as 3DGS's.
- Frame: glTF 2.0 core (section 3.4) is right-handed with +Y up. The scene is written as the .spz is (io/formats/
  spz.py): turned 180 degrees about x from the 3DGS/COLMAP frame (x right, y down, z forward), so y -> -y, z -> -z,
  quaternion (w, x, -y, -z) and the SH coefficients odd in y and z change sign; the reader turns it back.
- Container: glTF 2.0 core (section 4.4): a .glb is a 12-byte header (magic "glTF", version 2, length), a JSON chunk
  padded with spaces and a BIN chunk padded with zeros, each to 4 bytes. The .gltf names its buffer `<stem>.bin`,
  and never replaces a `<stem>.bin` that is not its own buffer (check_buffer_file).
- Reading: every part is checked as it is taken (gltf_parts.py); a buffer is read only from a .glb's own BIN chunk
  or from a plain file name beside the .gltf.

The extension is in `extensionsUsed` but not `extensionsRequired`: a reader without it still shows the points.
"""

from __future__ import annotations

import contextlib
import json
import struct
from pathlib import Path

import numpy as np

from ...errors import MCSplatError
from ..atomic import atomic_write_bytes, atomic_write_text
from .common import (AXES_FLIP, SH_FLIP, check_params, logit, normalized_quats,
                     read_bytes, sh_degree_of, sigmoid)
from .gltf_parts import FLOAT, TYPES, GltfParts, plain_file_name

EXTENSION = "KHR_gaussian_splatting"
PRIMITIVE_PROPERTIES = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
                        "sortingMethod": "cameraDistance"}
GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
ARRAY_BUFFER, POINTS = 34962, 0


def _sh_semantic(degree: int, coefficient: int) -> str:
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{coefficient}"


def _sh_semantics(degree: int) -> list[str]:
    """The rest coefficients' semantics in 3DGS order (degree 1's three, then degree 2's five, ...)."""
    return [_sh_semantic(d, m) for d in range(1, degree + 1) for m in range(2 * d + 1)]


def _attributes(params: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each attribute's float32 array in the glTF frame, by semantic."""
    flip_sh = SH_FLIP[:params["shN"].shape[1], None]
    quats = normalized_quats(params["quats"]) * np.array([1.0, 1.0, -1.0, -1.0])  # w x -y -z: turned about x
    attributes = {
        "POSITION": params["means"] * AXES_FLIP,
        f"{EXTENSION}:ROTATION": quats[:, [1, 2, 3, 0]],  # glTF's x, y, z, w
        f"{EXTENSION}:SCALE": np.exp(params["log_scales"].astype(np.float64)),
        f"{EXTENSION}:OPACITY": sigmoid(params["opacity_logits"]),
        _sh_semantic(0, 0): params["sh0"][:, 0, :],
    }
    rest = params["shN"] * flip_sh
    for index, semantic in enumerate(_sh_semantics(sh_degree_of(params["shN"]))):
        attributes[semantic] = rest[:, index, :]
    return {name: np.ascontiguousarray(values, dtype="<f4") for name, values in attributes.items()}


def _document(params: dict[str, np.ndarray], uri: str | None) -> tuple[dict, bytes]:
    """The glTF JSON and its one buffer's bytes (`uri`: the .bin's name, None in a .glb)."""
    n = check_params(params)
    views, accessors, chunks, offset, by_semantic = [], [], [], 0, {}
    for semantic, values in _attributes(params).items():
        data = values.tobytes()  # float32 arrays: every view starts 4-byte aligned
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": ARRAY_BUFFER})
        accessor = {"bufferView": len(views) - 1, "componentType": FLOAT, "count": n,
                    "type": TYPES[values.shape[1] if values.ndim == 2 else 1]}
        if semantic == "POSITION":  # the core specification requires POSITION's bounds
            accessor.update(min=values.min(axis=0).tolist(), max=values.max(axis=0).tolist())
        by_semantic[semantic] = len(accessors)
        accessors.append(accessor)
        chunks.append(data)
        offset += len(data)
    buffer = {"byteLength": offset} if uri is None else {"byteLength": offset, "uri": uri}
    primitive = {"attributes": by_semantic, "mode": POINTS, "extensions": {EXTENSION: dict(PRIMITIVE_PROPERTIES)}}
    document = {"asset": {"version": "2.0", "generator": "mcsplat"}, "extensionsUsed": [EXTENSION],
                "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "gaussians"}],
                "meshes": [{"name": "gaussians", "primitives": [primitive]}],
                "buffers": [buffer], "bufferViews": views, "accessors": accessors}
    return document, b"".join(chunks)


def _padded(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 4)


def write_glb(path: Path, params: dict[str, np.ndarray]) -> None:
    document, binary = _document(params, uri=None)
    text = _padded(json.dumps(document, separators=(",", ":")).encode(), b" ")
    binary = _padded(binary, b"\0")
    length = 12 + 8 + len(text) + 8 + len(binary)
    atomic_write_bytes(path, b"".join([struct.pack("<III", GLB_MAGIC, GLB_VERSION, length),
                                       struct.pack("<II", len(text), CHUNK_JSON), text,
                                       struct.pack("<II", len(binary), CHUNK_BIN), binary]))


def bin_file_of(path: Path) -> Path:
    """Where a .gltf's buffer goes: beside it, `<stem>.bin`."""
    return path.with_suffix(".bin")


def check_buffer_file(path: Path) -> None:
    """A .gltf's buffer replaces no file but the one the .gltf at `path` names as its buffer (the pair an export
    wrote before): never a `<stem>.bin` of anything else (COLMAP's cameras.bin, a file of the user's)."""
    buffer = bin_file_of(path)
    if not (buffer.exists() or buffer.is_symlink()) or (buffer.is_file() and _buffer_named_by(path) == buffer.name):
        return
    raise MCSplatError(f"{path}: its buffer would be written to {buffer}, which is there already and is not the "
                       f"buffer of {path.name}; export to another name, or move {buffer.name} away")


def _buffer_named_by(path: Path) -> object:
    """The uri of the buffer of the .gltf at `path`; None when there is no such file or it says none."""
    try:
        return json.loads(path.read_bytes())["buffers"][0]["uri"]
    except (OSError, ValueError, RecursionError, LookupError, TypeError):
        return None


def write_gltf(path: Path, params: dict[str, np.ndarray]) -> None:
    """The .bin first, then the .gltf that names it: a reader never finds a .gltf without its buffer."""
    check_buffer_file(path)
    document, binary = _document(params, uri=bin_file_of(path).name)
    atomic_write_bytes(bin_file_of(path), binary)
    atomic_write_text(path, json.dumps(document, indent=1) + "\n")


def _split_glb(path: Path) -> tuple[object, bytes]:
    """The JSON chunk parsed, and the BIN chunk's bytes (none when the file has no BIN chunk)."""
    data = read_bytes(path)
    if len(data) < 20 or struct.unpack_from("<II", data) != (GLB_MAGIC, GLB_VERSION):
        raise MCSplatError(f"{path}: not a glTF 2.0 binary (.glb) file")
    text_length, kind = struct.unpack_from("<II", data, 12)
    if kind != CHUNK_JSON:
        raise MCSplatError(f"{path}: the first chunk of a .glb must be its JSON")
    document = json.loads(data[20:20 + text_length])
    rest = data[20 + text_length:]
    binary = b""
    if len(rest) >= 8 and struct.unpack_from("<I", rest, 4)[0] == CHUNK_BIN:
        binary = rest[8:8 + struct.unpack_from("<I", rest)[0]]
    return document, binary


def _splat_primitive(parts: GltfParts) -> dict:
    """The first mesh primitive that names the KHR_gaussian_splatting extension."""
    for i, mesh in enumerate(parts.array(parts.document.get("meshes", []), "meshes")):
        where = f"meshes[{i}].primitives"
        for j, primitive in enumerate(parts.array(parts.object(mesh, f"meshes[{i}]").get("primitives"), where)):
            primitive = parts.object(primitive, f"{where}[{j}]")
            if EXTENSION in parts.object(primitive.get("extensions", {}), f"{where}[{j}].extensions"):
                return primitive
    raise MCSplatError(f"{parts.path}: no {EXTENSION} primitive")


def _gaussians(parts: GltfParts) -> dict[str, np.ndarray]:
    """The Gaussians of the first KHR_gaussian_splatting primitive, in our frame and raw parameters."""
    attributes = parts.object(_splat_primitive(parts).get("attributes"), f"its {EXTENSION} primitive's attributes")
    degree = max([d for d in range(1, 4) if _sh_semantic(d, 0) in attributes], default=0)
    widths = {"POSITION": 3, f"{EXTENSION}:ROTATION": 4, f"{EXTENSION}:SCALE": 3, f"{EXTENSION}:OPACITY": 1,
              _sh_semantic(0, 0): 3, **{semantic: 3 for semantic in _sh_semantics(degree)}}
    values = {}
    for semantic, width in widths.items():
        if semantic not in attributes:
            raise MCSplatError(f"{parts.path}: its {EXTENSION} primitive has no {semantic} attribute")
        values[semantic] = parts.float_rows(attributes[semantic], semantic, width)
    counts = {len(rows) for rows in values.values()}
    if len(counts) != 1:
        raise MCSplatError(f"{parts.path}: its {EXTENSION} attributes disagree on the number of Gaussians "
                           f"({sorted(counts)})")
    rest = [values[semantic] for semantic in _sh_semantics(degree)]
    n = counts.pop()
    shN = np.stack(rest, axis=1) * SH_FLIP[:len(rest), None] if rest else np.zeros((n, 0, 3))
    xyzw = values[f"{EXTENSION}:ROTATION"].astype(np.float64)
    return {
        "means": (values["POSITION"] * AXES_FLIP).astype(np.float32),
        "log_scales": np.log(np.maximum(values[f"{EXTENSION}:SCALE"].astype(np.float64), 1e-30)).astype(np.float32),
        "quats": (xyzw[:, [3, 0, 1, 2]] * np.array([1.0, 1.0, -1.0, -1.0])).astype(np.float32),
        "opacity_logits": logit(values[f"{EXTENSION}:OPACITY"][:, 0]).astype(np.float32),
        "sh0": values[_sh_semantic(0, 0)][:, None, :].astype(np.float32),
        "shN": shN.astype(np.float32),
    }


def holds_gaussians(path: Path) -> bool:
    """Whether a .glb or .gltf names the KHR_gaussian_splatting extension (else it is a mesh, or no glTF at all)."""
    try:
        document = _split_glb(path)[0] if path.suffix.lower() == ".glb" else json.loads(read_bytes(path))
    except (MCSplatError, ValueError, RecursionError, struct.error):
        return False
    used = document.get("extensionsUsed", []) if isinstance(document, dict) else []
    return isinstance(used, list) and EXTENSION in used


def read_glb(path: Path) -> dict[str, np.ndarray]:
    with _malformed_as_one_line(path):
        document, binary = _split_glb(path)
        parts = GltfParts(path, document)
        if "uri" in parts.buffer():  # glTF 2.0 core 4.4.3.3: a .glb's first buffer is its BIN chunk, named by no uri
            raise MCSplatError(f"{path}: its buffer names a uri, and a .glb's buffer is read from its own BIN chunk")
        parts.take_buffer(binary)
        return _gaussians(parts)


def read_gltf(path: Path) -> dict[str, np.ndarray]:
    with _malformed_as_one_line(path):
        parts = GltfParts(path, json.loads(read_bytes(path)))
        uri = parts.buffer().get("uri")
        if not plain_file_name(uri):  # never a folder, a path out of this one, or a data: URI
            shown = "none" if uri is None else repr(uri)[:40]
            raise MCSplatError(f"{path}: its buffer's uri must be the name of a file beside it (as x.bin), not "
                               f"{shown}; only such a buffer is read here")
        try:
            binary = read_bytes(path.parent / uri)
        except MCSplatError as error:  # named after the .gltf the user handed over, the .bin's own reason after
            raise MCSplatError(f"{path}: its buffer cannot be read ({error})") from None
        parts.take_buffer(binary)
        return _gaussians(parts)


@contextlib.contextmanager
def _malformed_as_one_line(path: Path):
    """What the parts' checks (gltf_parts.py) do not name, a bad JSON above all, is one line naming the file too."""
    try:
        yield
    except (KeyError, IndexError, TypeError, ValueError, RecursionError, struct.error) as error:
        reason = " ".join(str(error).split())[:120] or type(error).__name__
        raise MCSplatError(f"{path}: not a readable {EXTENSION} glTF ({type(error).__name__}: {reason})") from None
