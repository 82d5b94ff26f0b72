"""The check every group of options makes first as it is made: a float option that holds inf or nan is refused in one
line (inf passes every range check without an upper end, nan every comparison)."""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from typing import Any

from .errors import MCSplatError


@functools.cache
def _float_fields(cls: type) -> tuple[str, ...]:
    hints = typing.get_type_hints(cls)
    return tuple(f.name for f in dataclasses.fields(cls) if float in (hints[f.name], *typing.get_args(hints[f.name])))


def non_finite_options(options: Any, prefix: str = "") -> list[str]:
    """The float options of the dataclass `options` that hold inf or nan, as the command line gives them."""
    return [f"--{prefix}{name.replace('_', '-')} {value}" for name in _float_fields(type(options))
            if isinstance(value := getattr(options, name), float) and not math.isfinite(value)]


def refuse_non_finite(options: Any, prefix: str = "") -> None:
    found = non_finite_options(options, prefix)
    if found:
        raise MCSplatError(f"{', '.join(found)}: not a finite number; give one within the option's range (--help "
                           f"says it)")
