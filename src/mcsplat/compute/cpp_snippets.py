"""C++ for `wp.func_native`, kept in .cpp and .h files beside the module that compiles it (package data).

A snippet file holds the text Warp pastes into a native function's body. Where the text needs something from Python
(a constant such as TILE_SIZE, a shared prelude, code generated for the vector width) it says `{{NAME}}` (capitals,
digits and underscores), and `read_snippet` puts in the value given under that name:
- a placeholder alone on its line stands for whole lines: the line, its newline included, becomes the value (which
  must be empty or end with a newline);
- anywhere else, the placeholder becomes the value.
Values are put in as they are (a value's own text is not searched for placeholders); values no placeholder names are
left unused, so that files can share one set. A placeholder without a value is an error: what compiles is exactly the
file with the values in (the text that was written in Python before, but for a blank line of the projection's
backward).
"""

from __future__ import annotations

import importlib.resources
import re
from typing import Mapping

# Alone on its line (group 1), or inside one (group 2).
_PLACEHOLDER = re.compile(r"^\{\{([A-Z][A-Z0-9_]*)\}\}\n|\{\{([A-Z][A-Z0-9_]*)\}\}", re.MULTILINE)


def fill(text: str, values: Mapping[str, object], where: str = "snippet") -> str:
    """`text` with every {{NAME}} replaced by str(values[NAME]), as the module docstring says."""
    given = {name: str(value) for name, value in values.items()}

    def value(match: re.Match) -> str:
        name = match.group(1) or match.group(2)
        if name not in given:
            raise ValueError(f"{where}: no value given for {{{{{name}}}}}")
        filled = given[name]
        if match.group(1) and filled and not filled.endswith("\n"):
            raise ValueError(f"{where}: {{{{{name}}}}} stands alone on its line, so its value must be whole lines "
                             f"(end with a newline)")
        return filled

    return _PLACEHOLDER.sub(value, text)


def read_snippet(package: str | None, name: str, values: Mapping[str, object] | None = None) -> str:
    """The snippet file `name` of `package` (the caller's __package__: the file lies beside it) with its placeholders
    filled from `values`."""
    if not package:
        raise ValueError(f"read_snippet({name!r}): give the package the file lies in (__package__)")
    text = importlib.resources.files(package).joinpath(name).read_text(encoding="utf-8")
    return fill(text, values or {}, where=f"{package}/{name}")
