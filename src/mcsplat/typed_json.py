"""Whether a value read back from config.json has the type its option is declared with.

A dataclass takes whatever it is given, so a hand-edited `"steps": "300"` would only fail deep inside the first step
that compares it with a number; checked here, it is a one-line error that names the option.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import tyro


@functools.cache
def option_types(cls: type) -> dict[str, Any]:
    """The declared type of each field of the dataclass `cls`."""
    hints = typing.get_type_hints(cls, include_extras=False)
    return {field.name: hints[field.name] for field in dataclasses.fields(cls)}


@functools.cache
def flat_groups(cls: type) -> tuple[str, ...]:
    """The fields of the dataclass `cls` that are groups of options whose flags have no prefix
    (tyro.conf.OmitArgPrefixes: --surface-from, not --surface-terms.surface-from): config.json keeps their options
    beside `cls`'s own, under their own names, as the command line gives them."""
    hints = typing.get_type_hints(cls, include_extras=True)
    return tuple(f.name for f in dataclasses.fields(cls)
                 if typing.get_origin(hints[f.name]) is Annotated
                 and any(mark is tyro.conf.OmitArgPrefixes for mark in hints[f.name].__metadata__))


def fits(value: Any, hint: Any) -> bool:
    """Whether the JSON value `value` can stand for a value of type `hint` (a list for a tuple, a string for a
    Path); types this does not know are let through."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return any(fits(value, arg) for arg in args)
    if origin is Literal:
        return any(value == arg and type(value) is type(arg) for arg in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint in (str, Path):
        return isinstance(value, str)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(fits(item, args[0]) for item in value)
        return len(value) == len(args) and all(fits(item, arg) for item, arg in zip(value, args))
    return True


def describe(hint: Any) -> str:
    """`hint` in words, for the error message."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join(describe(arg) for arg in args)
    if origin is Literal:
        return " or ".join(repr(arg) for arg in args)
    if origin is tuple:
        return "a list" if len(args) == 2 and args[1] is Ellipsis else f"a list of {len(args)} values"
    names = {type(None): "null", bool: "true or false", int: "a whole number", float: "a number", str: "a string",
             Path: "a path"}
    return names.get(hint, getattr(hint, "__name__", str(hint)))


def checked_dataclass(cls: type, values: Any, source: str, prefix: str = "", nested: dict[str, type] | None = None,
                      complete: bool = False) -> Any:
    """An instance of the dataclass `cls` made from the JSON object `values` that `source` (config.json) holds under
    `prefix`, each value checked against its field's declared type: an unknown key, a value of another type, one the
    class refuses, or (`complete`: a record mcsplat always writes whole) a missing key is a one-line error naming it.
    `nested`: the fields that are dataclasses too, by name; lists become tuples, strings paths where a path is
    declared. Fields not saved (metadata saved=False) are unknown keys here."""
    from .errors import MCSplatError

    where = prefix.rstrip(".") or "the file"
    if not isinstance(values, dict):
        raise MCSplatError(f"{source}: {where} must be an object {{...}}")
    flat = flat_groups(cls)
    if flat:  # the options of a group without prefix sit beside cls's own: gathered into the group here
        values, nested = dict(values), dict(nested or {})
        hints_of = option_types(cls)
        for group in flat:
            if group in values:  # the group is no key of the file: its options are
                raise MCSplatError(f"{source}: unknown option {prefix + group!r} (written by another mcsplat "
                                   f"version?)")
            names = {f.name for f in dataclasses.fields(hints_of[group])}
            values[group] = {key: values.pop(key) for key in list(values) if key in names}
            nested[group] = hints_of[group]
    hints = {name: hint for name, hint in option_types(cls).items()
             if next(f for f in dataclasses.fields(cls) if f.name == name).metadata.get("saved", True)}
    missing = sorted(hints.keys() - values.keys()) if complete else []
    if missing:
        raise MCSplatError(f"{source}: {where} lacks {', '.join(missing)} (written by another mcsplat version?)")
    kwargs = {}
    for key, value in values.items():
        if key not in hints:
            raise MCSplatError(f"{source}: unknown option {prefix + key!r} (written by another mcsplat version?)")
        hint = hints[key]
        if nested and key in nested:
            inner = prefix if key in flat else f"{prefix}{key}."
            value = checked_dataclass(nested[key], value, source, inner, complete=complete)
        elif not fits(value, hint):
            raise MCSplatError(f"{source}: {prefix}{key} is {json.dumps(value)}, not {describe(hint)}; put back the "
                               f"value mcsplat wrote there")
        elif isinstance(value, str) and _declares_path(hint):
            value = Path(value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[key] = value
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as error:  # MCSplatError (the class's own checks) passes through
        raise MCSplatError(f"{source}: {prefix}{error}; put back the value mcsplat wrote there") from None


def _declares_path(hint: Any) -> bool:
    return hint is Path or Path in typing.get_args(hint)
