"""Every kind of per-view input, by name: a new kind is one module beside this one and one line here."""

from __future__ import annotations

from typing import Sequence

from . import depth, masks
from .kind import Kind

KINDS: dict[str, Kind] = {kind.name: kind for kind in (
    masks.KIND,
    depth.KIND,
)}


def kind_for(options: object) -> Kind:
    """The kind that an options object (MaskOptions, DepthOptions ...) asks for."""
    for kind in KINDS.values():
        if isinstance(options, kind.options):
            return kind
    raise TypeError(f"{type(options).__name__} asks for no kind of per-view input; give the options of one of "
                    f"{', '.join(KINDS)} ({', '.join(kind.options.__name__ for kind in KINDS.values())})")


def with_defaults(requests: Sequence[object]) -> list[object]:
    """`requests` and the default request of each kind they do not ask for (masks: the scene's masks/ folder), in
    the order of KINDS (the order of the scene's notes)."""
    asked = dict(zip((kind.name for kind in kinds_for(requests)), requests))
    return [asked.get(name, kind.default) for name, kind in KINDS.items()
            if asked.get(name, kind.default) is not None]


def kinds_for(requests: Sequence[object]) -> list[Kind]:
    """The kind each request asks for; a request that asks for none, or two for one kind, is a caller's mistake."""
    kinds = [kind_for(options) for options in requests]
    if len({kind.name for kind in kinds}) < len(kinds):
        raise ValueError(f"one request per kind of per-view input, got {[kind.name for kind in kinds]}")
    return kinds
