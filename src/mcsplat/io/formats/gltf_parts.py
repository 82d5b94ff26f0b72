"""The parts of a glTF document that io/formats/gltf.py reads, each checked as it is taken.

A file handed to `mcsplat view` may be anything: a part of the wrong type, an index outside its list, a buffer that
is not a plain file beside the .gltf, an accessor that reads outside its buffer view or a view outside its buffer
is one line naming the file and the part (glTF 2.0 core, sections 3.6: buffers and buffer views, 3.6.2: accessors),
never a traceback nor values read from the wrong bytes.
"""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

import numpy as np

from ...errors import MCSplatError

FLOAT = 5126  # componentType float32, the only one read and written here
TYPES = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}  # an accessor's type by its number of components


def plain_file_name(uri: object) -> bool:
    """Whether a buffer's uri names a file in the .gltf's own folder: not a path, not a data: or other URI."""
    return (isinstance(uri, str) and uri not in ("", ".", "..")
            and not any(character in uri for character in "/\\:\0"))


def _kind(value: object) -> str:
    """What a JSON value is, in the file's terms."""
    if value is None:
        return "missing or null"
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean"}.get(type(value), "a number")


def _shown(value: object) -> str:
    return "missing or null" if value is None else repr(value)[:40]


class GltfParts:
    """A glTF document and (once taken) its one buffer's bytes, read part by part."""

    def __init__(self, path: Path, document: object):
        self.path = path
        self.document = self.object(document, "the document")
        self.binary = b""

    def fail(self, reason: str) -> NoReturn:
        raise MCSplatError(f"{self.path}: a malformed glTF: {reason}")

    def object(self, value: object, where: str) -> dict:
        if not isinstance(value, dict):
            self.fail(f"{where} is {_kind(value)}, not an object")
        return value

    def array(self, value: object, where: str) -> list:
        if not isinstance(value, list):
            self.fail(f"{where} is {_kind(value)}, not a list")
        return value

    def whole(self, value: object, where: str) -> int:
        """A count, an index or a byte offset: an integer of 0 or more (JSON's true is no number here)."""
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            self.fail(f"{where} is {_shown(value)}, not a whole number")
        return value

    def item(self, kind: str, index: object, where: str) -> dict:
        """`document[kind][index]`, an object, by an index within the list."""
        items = self.array(self.document.get(kind), kind)
        if self.whole(index, where) >= len(items):
            self.fail(f"{where} is {index}, past the end of {kind}, which holds {len(items)}")
        return self.object(items[index], f"{kind}[{index}]")

    def buffer(self) -> dict:
        """The first buffer, the one read (a .glb's BIN chunk, or the .bin beside a .gltf)."""
        buffers = self.array(self.document.get("buffers"), "buffers")
        if not buffers:
            self.fail("buffers is empty")
        return self.object(buffers[0], "buffers[0]")

    def take_buffer(self, data: bytes) -> None:
        """The buffer's bytes: `data` (the .bin, or the .glb's BIN chunk) holds at least the byteLength declared."""
        length = self.whole(self.buffer().get("byteLength"), "the buffer's byteLength")
        if len(data) < length:
            self.fail(f"its buffer declares {length:,} bytes and holds {len(data):,}: the file is cut short")
        self.binary = data[:length]

    def float_rows(self, index: object, what: str, width: int) -> np.ndarray:
        """Accessor `index`'s float32 values as rows [count, width], only from bytes its buffer view holds."""
        where = f"accessors[{index}] ({what})"
        accessor = self.item("accessors", index, f"the accessor of {what}")
        if accessor.get("componentType") != FLOAT:
            self.fail(f"{where} is not float32 (quantised attributes are not read here)")
        if accessor.get("type") != TYPES[width]:
            self.fail(f"{where} is of type {_shown(accessor.get('type'))}, and {what} is a {TYPES[width]}")
        if "sparse" in accessor:
            self.fail(f"{where} is sparse, which is not read here")
        count = self.whole(accessor.get("count"), f"{where}'s count")
        offset = self.whole(accessor.get("byteOffset", 0), f"{where}'s byteOffset")
        view_index = accessor.get("bufferView")
        view = self.item("bufferViews", view_index, f"{where}'s bufferView")
        view_where = f"bufferViews[{view_index}]"
        if view.get("buffer") != 0:
            self.fail(f"{view_where} is of buffer {_shown(view.get('buffer'))}; only buffer 0 is read here")
        if view.get("byteStride", 4 * width) != 4 * width:
            self.fail(f"{view_where} interleaves attributes (byteStride {_shown(view.get('byteStride'))}), which "
                      f"is not read here")
        start = self.whole(view.get("byteOffset", 0), f"{view_where}'s byteOffset")
        length = self.whole(view.get("byteLength"), f"{view_where}'s byteLength")
        if start + length > len(self.binary):
            self.fail(f"{view_where} ends at byte {start + length:,}, past its buffer's {len(self.binary):,}")
        if (start + offset) % 4:
            self.fail(f"{where} starts at byte {start + offset:,}, and float32 values start at a multiple of 4")
        if offset + count * width * 4 > length:
            self.fail(f"{where} reads {count:,} values of {width * 4} bytes from byte {offset:,} of {view_where}, "
                      f"which holds {length:,}")
        return np.frombuffer(self.binary, "<f4", count * width, start + offset).reshape(count, width)
