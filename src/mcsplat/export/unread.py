"""An option that the chosen format does not read (--spz-version for a .ply, a mesh option for Gaussians, a choice of
Gaussians for the mesh) is refused in one line: taken without a word, it would be ignored.

An option counts as given when it differs from its default: one given at its default value changes nothing. A group
of options (selection, mesh) is read or not as a whole, as the formats' table says.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator

from ..errors import MCSplatError
from .formats import EXPORT_FORMATS, ExportFormat
from .options import ExportOptions


def refuse_unread_options(chosen: ExportFormat, options: ExportOptions) -> None:
    from ..run.start import option_text

    by_readers: dict[tuple[str, ...], list[str]] = {}
    for reader_key, name, value, default in _given(options):
        if _read_by_some_only(reader_key) and reader_key not in chosen.reads and value != default:
            by_readers.setdefault(_readers(reader_key), []).append(option_text(name, value))
    if not by_readers:
        return
    unread = "; ".join(f"{', '.join(texts)} (read by {_described(readers)})" for readers, texts in by_readers.items())
    them = "it" if sum(map(len, by_readers.values())) == 1 else "them"
    raise MCSplatError(f"{unread}: this export writes a {chosen.name} file, which would ignore {them}; leave {them} "
                       f"out, or export the format that reads {them}")


def _given(options: ExportOptions) -> Iterator[tuple[str, str, Any, Any]]:
    """(the name the table's `reads` knows it by, the option's name, its value, its default) of every option."""
    for outer in dataclasses.fields(options):
        value = getattr(options, outer.name)
        if dataclasses.is_dataclass(value):  # a group: its options, each known to the table by the group's name
            for inner in dataclasses.fields(value):
                yield outer.name, inner.name, getattr(value, inner.name), inner.default
        else:
            yield outer.name, outer.name, value, outer.default


def _read_by_some_only(name: str) -> bool:
    return any(name in entry.reads for entry in EXPORT_FORMATS.values())


def _readers(name: str) -> tuple[str, ...]:
    return tuple(entry.name for entry in EXPORT_FORMATS.values() if name in entry.reads)


def _described(readers: tuple[str, ...]) -> str:
    """`spz only`, or `every format but mesh` when that is shorter."""
    others = [name for name in EXPORT_FORMATS if name not in readers]
    if len(readers) <= len(others):
        return f"{' and '.join(readers)} only"
    return f"every format but {' and '.join(others)}"
