"""Images a scene (or a folder of photos) holds twice: the same file listed again, or a byte-identical copy of it.

A repeat would be one view twice: trained on twice as often, or, worse, a test view that is also trained on (an
inflated score). Every loader (through assemble) and `mcsplat process` keep the first of each image and name the rest.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Sequence


def first_copies(paths: Sequence[Path]) -> tuple[list[int], dict[int, int]]:
    """(the indices of the first path of each distinct image, in order; each repeat's index -> its original's)."""
    first: dict[object, int] = {}
    kept, repeats = [], {}
    for index, identity in enumerate(_identities(paths)):
        if identity in first:
            repeats[index] = first[identity]
        else:
            first[identity] = index
            kept.append(index)
    return kept, repeats


def _identities(paths: Sequence[Path]) -> list[object]:
    """What makes two image files one image: the file itself, or its bytes where another file has its size (only
    those are read: files of different sizes differ)."""
    files = [Path(path).resolve() for path in paths]
    by_size: dict[int, set[Path]] = {}
    for file in files:
        by_size.setdefault(file.stat().st_size, set()).add(file)
    digests = {file: _digest(file) for group in by_size.values() if len(group) > 1 for file in group}
    return [digests.get(file, file) for file in files]


def _digest(file: Path) -> str:
    digest = hashlib.sha256()
    with file.open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def describe(repeat: str, original: str) -> str:
    """'b.png, a copy of a.png', or 'a.png' for a file listed twice."""
    return repeat if repeat == original else f"{repeat}, a copy of {original}"
