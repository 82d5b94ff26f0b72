"""PlayCanvas's SOG ("Spatially Ordered Gaussians", version 2), read by the PlayCanvas engine, SuperSplat,
@playcanvas/splat-transform and Spark: a zip (sog_bundle.py) of `meta.json` and lossless WebP images of quantised
attributes. Every image but the SH palette holds one texel per Gaussian, row-major from the top left, W x H with
W = ceil(sqrt(N) / 4) * 4 and H = ceil(N / W / 4) * 4; the texels after the N-th are zero.

    meta.json      {"version": 2, "asset": {"generator": ...}, "count": N,
                    "means": {"mins": [3], "maxs": [3], "files": ["means_l.webp", "means_u.webp"]},
                    "scales": {"codebook": [256], "files": ["scales.webp"]}, "quats": {"files": ["quats.webp"]},
                    "sh0": {"codebook": [256], "files": ["sh0.webp"]},
                    "shN": {"count": P, "bands": SH degree, "codebook": [256],
                            "files": ["shN_centroids.webp", "shN_labels.webp"]}}       (shN: SH degree 1-3 only)
                   and, for a scene trained with the 2D filter, "model": "antialiased" (splat-transform 3.x) and
                   "antialias": true (the v2 draft, Spark)
    means_l, _u    RGB: the low and the high byte of round(65535 (t - min) / (max - min)) for x, y, z, where
                   t = sign(v) ln(|v| + 1) (fine steps near the centre, coarse far out) and min / max are t's bounds
    quats          RGB: q / |q| (w, x, y, z) with the largest |component| made positive; the other three in that
                   order, each round(255 (v sqrt(2) / 2 + 0.5)) (they lie within +-sqrt(1/2));
                   A: 252 + the index of the largest (0 w, 1 x, 2 y, 3 z)
    scales         RGB: the index in scales' codebook of the log-scale on x, y, z
    sh0            RGB: the index in sh0's codebook of f_dc (the SH DC coefficient); A: round(sigmoid(opacity) 255)
    shN_labels     RG: the Gaussian's entry of the SH palette, a 16-bit number, low byte in R
    shN_centroids  the palette, 64 entries a row: entry i at row i // 64, texels (i % 64) (K-1) + j for its
                   coefficients j < K-1, RGB the indices in shN's codebook of coefficient j's r, g, b

A codebook is 256 values (codebook.py: 1D k-means over the values of all three axes or channels); the palette is a
k-means of the Gaussians' 3(K-1) SH coefficients, weighted by opacity, with P entries (palette_size: every Gaussian
its own up to 1,024, then about N / 16, at most 65,536 as the 16-bit labels allow). Gaussians are written in Morton
order of their centres (compressed_ply.morton_order), so that neighbours in space are neighbours in the images,
which WebP compresses better. Axes: the .ply's own, unturned. (The specification names x right, y up, z back, but
splat-transform writes a .ply's values into a .sog as they are and PlayCanvas turns the two alike when it draws
them: a .sog made here shows as the .ply does.) The layout follows PlayCanvas's specification
(developer.playcanvas.com, "The SOG Format") and splat-transform 3.7.0's reader and writer.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ... import __version__
from ...errors import MCSplatError
from .codebook import scalar_codebook, vector_palette
from .common import bases_of, check_params, logit, normalized_quats, read_bytes, sh_degree_of, sigmoid
from .compressed_ply import morton_order
from .sog_bundle import Bundle, write_bundle

VERSION = 2
CODEBOOK_SIZE = 256
PALETTE_ROW = 64               # palette entries in a row of shN_centroids
LARGEST_TAG = 252              # quats' alpha is 252 + the index of the largest component
MAX_PALETTE = 1 << 16          # the labels are 16-bit
MAX_WEBP_SIDE = 16383
# k-means steps of the SH palette: splat-transform's default of 10 gains next to nothing on the demo for far more time,
# and the palette is most of a large scene's export on a CPU (docs/outputs.md, "Export formats").
PALETTE_ITERATIONS = 5
_ROOT_HALF = math.sqrt(0.5)


def palette_size(count: int) -> int:
    """Entries of the SH palette for `count` Gaussians: each its own up to 1,024; then the power of two nearest
    count / 16 (splat-transform's choice for large scenes), at least 1,024 and at most 65,536."""
    if count <= 1024:
        return count
    return min(MAX_PALETTE, max(1024, 1 << round(math.log2(count / 16))))


def image_size(count: int) -> tuple[int, int]:
    """(width, height) of the per-Gaussian images: a square-ish grid in multiples of 4 texels."""
    width = math.ceil(math.sqrt(count) / 4) * 4
    if width > MAX_WEBP_SIDE:
        raise MCSplatError(f"{count:,} Gaussians need images of {width:,} texels a side, more than WebP's "
                           f"{MAX_WEBP_SIDE:,}: export fewer (--max-gaussians) or another format")
    return width, math.ceil(count / width / 4) * 4


def log_transform(values: np.ndarray) -> np.ndarray:
    return np.sign(values) * np.log1p(np.abs(values))


def _texels(columns: list[np.ndarray], count: int) -> np.ndarray:
    """The per-Gaussian image of `columns` (uint8, one a channel), zero after the count-th texel."""
    width, height = image_size(count)
    pixels = np.zeros((width * height, len(columns)), dtype=np.uint8)
    pixels[:count] = np.stack(columns, axis=1)
    return pixels.reshape(height, width, len(columns))


def _means(means: np.ndarray) -> tuple[dict, dict[str, np.ndarray]]:
    t = log_transform(means.astype(np.float64))
    lo, hi = t.min(axis=0), t.max(axis=0)
    steps = np.round(65535.0 * (t - lo) / np.where(hi > lo, hi - lo, 1.0)).astype(np.uint16)
    n = len(means)
    images = {"means_l.webp": _texels([(steps[:, a] & 0xFF).astype(np.uint8) for a in range(3)], n),
              "means_u.webp": _texels([(steps[:, a] >> 8).astype(np.uint8) for a in range(3)], n)}
    return {"mins": lo.tolist(), "maxs": hi.tolist(), "files": list(images)}, images


def _quats(quats_wxyz: np.ndarray) -> np.ndarray:
    q = normalized_quats(quats_wxyz)
    largest = np.argmax(np.abs(q), axis=1)
    rows = np.arange(len(q))
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[i for i in range(4) if i != m] for m in range(4)])[largest]  # the three kept, in order
    kept = q[rows[:, None], others]
    codes = np.clip(np.round(255.0 * (kept / _ROOT_HALF * 0.5 + 0.5)), 0, 255).astype(np.uint8)
    return _texels([*codes.T, (LARGEST_TAG + largest).astype(np.uint8)], len(q))


def _sh_palette(rest: np.ndarray, opacity: np.ndarray) -> tuple[dict, dict[str, np.ndarray]]:
    """shN's meta and images for the SH rest coefficients [N, K-1, 3], each Gaussian weighing as its opacity."""
    n, coefficients = rest.shape[:2]
    # A palette row is coefficient-major then r g b, as the centroids' texels hold them.
    centroids, labels = vector_palette(rest.reshape(n, -1), palette_size(n), weights=opacity,
                                       iterations=PALETTE_ITERATIONS)
    codebook, codes = scalar_codebook(centroids)
    entries = len(centroids)
    rows = math.ceil(entries / PALETTE_ROW)
    palette = np.zeros((rows * PALETTE_ROW, coefficients, 3), dtype=np.uint8)
    palette[:entries] = codes.reshape(entries, coefficients, 3)
    images = {"shN_centroids.webp": palette.reshape(rows, PALETTE_ROW * coefficients, 3),
              "shN_labels.webp": _texels([(labels & 0xFF).astype(np.uint8), (labels >> 8).astype(np.uint8),
                                          np.zeros(n, np.uint8)], n)}
    meta = {"count": entries, "bands": sh_degree_of(rest), "codebook": codebook.tolist(), "files": list(images)}
    return meta, images


def write_sog(path: Path, params: dict[str, np.ndarray], antialiased: bool = False) -> None:
    n = check_params(params)
    order = morton_order(params["means"].astype(np.float64))
    g = {key: value[order] for key, value in params.items()}
    means_meta, images = _means(g["means"])
    images["quats.webp"] = _quats(g["quats"])
    scale_codebook, scale_codes = scalar_codebook(g["log_scales"])
    images["scales.webp"] = _texels(list(scale_codes.T), n)
    colour_codebook, colour_codes = scalar_codebook(g["sh0"][:, 0, :])
    alpha = np.clip(np.round(sigmoid(g["opacity_logits"]) * 255.0), 0, 255).astype(np.uint8)
    images["sh0.webp"] = _texels([*colour_codes.T, alpha], n)
    meta = {"version": VERSION, "asset": {"generator": f"mcsplat {__version__}"}, "count": n}
    if antialiased:
        meta.update(model="antialiased", antialias=True)
    meta.update(means=means_meta, scales={"codebook": scale_codebook.tolist(), "files": ["scales.webp"]},
                quats={"files": ["quats.webp"]}, sh0={"codebook": colour_codebook.tolist(), "files": ["sh0.webp"]})
    if g["shN"].shape[1]:
        meta["shN"], sh_images = _sh_palette(g["shN"], sigmoid(g["opacity_logits"]))
        images.update(sh_images)
    write_bundle(path, meta, images)


def read_sog(path: Path) -> dict[str, np.ndarray]:
    """A version-2 .sog, its Gaussians in the file's order; a damaged file is one MCSplatError naming it."""
    bundle = Bundle(path, read_bytes(path))
    fields = _MetaFields(path, bundle.meta)
    n = fields.count()
    means_lo, means_hi = (fields.texels(bundle, "means", i, n) for i in (0, 1))
    mins, maxs = (np.array(fields.numbers("means", key, 3)) for key in ("mins", "maxs"))
    steps = means_lo[:, :3].astype(np.float64) + 256.0 * means_hi[:, :3]
    t = mins + np.where(maxs > mins, maxs - mins, 1.0) * steps / 65535.0
    quat_texels = fields.texels(bundle, "quats", 0, n)
    scales = np.array(fields.numbers("scales", "codebook", CODEBOOK_SIZE))[fields.texels(bundle, "scales", 0, n)[:, :3]]
    sh0_texels = fields.texels(bundle, "sh0", 0, n)
    colours = np.array(fields.numbers("sh0", "codebook", CODEBOOK_SIZE))[sh0_texels[:, :3]]
    return {
        "means": (np.sign(t) * np.expm1(np.abs(t))).astype(np.float32),
        "log_scales": scales.astype(np.float32),
        "quats": _unpack_quats(path, quat_texels).astype(np.float32),
        "opacity_logits": logit(sh0_texels[:, 3] / 255.0).astype(np.float32),
        "sh0": colours[:, None, :].astype(np.float32),
        "shN": _read_sh(bundle, fields, n).astype(np.float32),
    }


def _unpack_quats(path: Path, texels: np.ndarray) -> np.ndarray:
    largest = texels[:, 3].astype(np.int64) - LARGEST_TAG
    if ((largest < 0) | (largest > 3)).any():
        raise MCSplatError(f"{path}: quats.webp has alpha values outside {LARGEST_TAG}-255; the file is damaged")
    kept = (texels[:, :3] / 255.0 * 2.0 - 1.0) * _ROOT_HALF
    others = np.array([[i for i in range(4) if i != m] for m in range(4)])[largest]
    q = np.zeros((len(texels), 4))
    rows = np.arange(len(texels))
    q[rows[:, None], others] = kept
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (kept ** 2).sum(axis=1)))
    return q


def _read_sh(bundle: Bundle, fields: _MetaFields, n: int) -> np.ndarray:
    if "shN" not in bundle.meta:
        return np.zeros((n, 0, 3))
    degree = fields.whole("shN", "bands", 1, 3)
    coefficients = bases_of(degree)
    entries = fields.whole("shN", "count", 1, MAX_PALETTE)
    codebook = np.array(fields.numbers("shN", "codebook", CODEBOOK_SIZE))
    palette = bundle.image(fields.files("shN")[0])
    rows = math.ceil(entries / PALETTE_ROW)
    if palette.shape[1] != PALETTE_ROW * coefficients or palette.shape[0] < rows:
        raise MCSplatError(f"{bundle.path}: shN_centroids is {palette.shape[1]} x {palette.shape[0]} texels; "
                           f"{entries:,} entries of SH degree {degree} need {PALETTE_ROW * coefficients} x {rows}")
    entries_rgb = palette[:rows, :, :3].reshape(rows * PALETTE_ROW, coefficients, 3)[:entries]
    label_texels = fields.texels(bundle, "shN", 1, n)
    labels = label_texels[:, 0].astype(np.int64) + 256 * label_texels[:, 1].astype(np.int64)
    if labels.max() >= entries:
        raise MCSplatError(f"{bundle.path}: shN_labels points past the {entries:,} palette entries; the file is "
                           "damaged")
    return codebook[entries_rgb[labels]]


class _MetaFields:
    """meta.json's fields, each checked as it is read: a missing or malformed one is one line naming it."""

    def __init__(self, path: Path, meta: dict):
        self.path, self.meta = path, meta
        if meta.get("version") != VERSION:
            found = f"version {meta['version']!r}" if "version" in meta else "no version (SOG version 1)"
            raise MCSplatError(f"{path}: its meta.json says {found}; SOG version {VERSION} is read (splat-transform "
                               "converts older ones)")

    def _entry(self, group: str, key: str):
        entry = self.meta.get(group)
        if not isinstance(entry, dict) or key not in entry:
            raise MCSplatError(f"{self.path}: meta.json has no {group}.{key}")
        return entry[key]

    def whole(self, group: str, key: str, low: int, high: int) -> int:
        value = self._entry(group, key)
        if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
            raise MCSplatError(f"{self.path}: meta.json's {group}.{key} is {value!r}, not a whole number in "
                               f"{low}-{high}")
        return value

    def numbers(self, group: str, key: str, length: int) -> list[float]:
        value = self._entry(group, key)
        if (not isinstance(value, list) or len(value) != length
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                           for v in value)):
            raise MCSplatError(f"{self.path}: meta.json's {group}.{key} is not a list of {length} finite numbers")
        return value

    def files(self, group: str) -> list:
        value = self._entry(group, "files")
        if not isinstance(value, list) or not value:
            raise MCSplatError(f"{self.path}: meta.json's {group}.files is not a list of file names")
        return value

    def count(self) -> int:
        value = self.meta.get("count")
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise MCSplatError(f"{self.path}: meta.json's count is {value!r}, not a number of Gaussians")
        return value

    def texels(self, bundle: Bundle, group: str, index: int, count: int) -> np.ndarray:
        """The first `count` texels [count, 4] of the index-th image of `group`."""
        names = self.files(group)
        if index >= len(names):
            raise MCSplatError(f"{self.path}: meta.json's {group}.files names {len(names)} images, not "
                               f"{index + 1}")
        image = bundle.image(names[index])
        if image.shape[0] * image.shape[1] < count:
            raise MCSplatError(f"{self.path}: {names[index]} has {image.shape[0] * image.shape[1]:,} texels for "
                               f"{count:,} Gaussians")
        return image.reshape(-1, 4)[:count]
