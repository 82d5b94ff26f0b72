"""The container of a `.sog`: a zip of `meta.json` and lossless WebP images (Pillow's libwebp), and the images read
back as RGBA arrays. Members are stored, not deflated (WebP is compressed already, as splat-transform stores them),
with a fixed date so that the same scene gives the same bytes. A damaged bundle is one MCSplatError naming it."""

from __future__ import annotations

import io
import json
import zipfile
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ...errors import MCSplatError
from ..atomic import atomic_path

META = "meta.json"
_DATE = (1980, 1, 1, 0, 0, 0)  # the earliest a zip can say
# What a damaged zip member or image raises while it is read: a bad CRC, a cut stream, a missing name, bad pixels.
_DAMAGE = (KeyError, zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError,
           UnidentifiedImageError, Image.DecompressionBombError)


def webp_bytes(pixels: np.ndarray) -> bytes:
    """Lossless WebP of an H x W x 3 (RGB) or 4 (RGBA) uint8 array. `exact` keeps the colour of texels whose alpha
    is 0 (a Gaussian of opacity below 1/510 still has its colour codes in sh0's RGB)."""
    buffer = io.BytesIO()
    Image.fromarray(pixels, "RGBA" if pixels.shape[2] == 4 else "RGB").save(
        buffer, format="WEBP", lossless=True, quality=100, method=4, exact=True)
    return buffer.getvalue()


def write_bundle(path: Path, meta: dict, images: dict[str, np.ndarray]) -> None:
    """`path`, atomically: meta.json first (a reader that streams the zip learns the file names before the images),
    then each image as a lossless WebP."""
    members = [(META, json.dumps(meta, separators=(",", ":")).encode())]
    members += [(name, webp_bytes(pixels)) for name, pixels in images.items()]
    with atomic_path(path, size_hint=sum(len(data) for _, data in members) + 4096) as tmp:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as bundle:
            for name, data in members:
                bundle.writestr(zipfile.ZipInfo(name, date_time=_DATE), data)


class Bundle:
    """A .sog read into memory: its meta.json and, on demand, its images as RGBA arrays."""

    def __init__(self, path: Path, data: bytes):
        self.path = path
        try:
            self._zip = zipfile.ZipFile(io.BytesIO(data))
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as error:
            raise MCSplatError(f"{path}: not a .sog file (not a readable zip archive: {error})") from None
        try:
            self.meta = json.loads(self._member(META))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise MCSplatError(f"{path}: its meta.json is not JSON ({error})") from None
        if not isinstance(self.meta, dict):
            raise MCSplatError(f"{path}: its meta.json is not a JSON object")

    def _member(self, name: str) -> bytes:
        try:
            return self._zip.read(name)
        except KeyError:
            raise MCSplatError(f"{self.path}: the .sog holds no {name}") from None
        except _DAMAGE as error:
            raise MCSplatError(f"{self.path}: {name} inside the .sog is damaged ({error})") from None

    def image(self, name: object) -> np.ndarray:
        """The member `name` decoded as an H x W x 4 uint8 array."""
        if not isinstance(name, str):
            raise MCSplatError(f"{self.path}: meta.json names an image as {name!r}, not a file name")
        data = self._member(name)
        try:
            with Image.open(io.BytesIO(data)) as image:
                return np.asarray(image.convert("RGBA"))
        except _DAMAGE as error:
            raise MCSplatError(f"{self.path}: {name} inside the .sog is not a readable image ({error})") from None
