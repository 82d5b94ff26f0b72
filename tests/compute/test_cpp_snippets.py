"""The C++ files of the CPU kernels (compute/cpp_snippets.py): placeholders filled as documented, a missing value
refused, and every file read by a module and shipped with the package."""

from __future__ import annotations

from pathlib import Path

import pytest

from mcsplat.compute.cpp_snippets import fill, read_snippet

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "src" / "mcsplat"
CPP_FILES = sorted(p for p in PACKAGE.rglob("*") if p.suffix in (".cpp", ".h"))


def test_placeholders_are_filled_inline_and_as_whole_lines():
    text = "    int a = {{N}};\n{{BLOCK}}\n    return;\n{{EMPTY}}\n"
    filled = fill(text, {"N": 16, "BLOCK": "    a += 1;\n    a *= 2;\n", "EMPTY": "", "UNUSED": 1})
    assert filled == "    int a = 16;\n    a += 1;\n    a *= 2;\n    return;\n"
    # A value is put in as it is: a placeholder inside it stays.
    assert fill("x = {{A}};", {"A": "{{B}}"}) == "x = {{B}};"
    # C++'s own braces are not placeholders.
    assert fill("float m[2][2] = {{a, b}, {c, d}};", {}) == "float m[2][2] = {{a, b}, {c, d}};"


def test_a_placeholder_without_a_value_is_refused():
    with pytest.raises(ValueError, match=r"no value given for \{\{TILE_SIZE\}\}"):
        fill("int t = {{TILE_SIZE}};", {"TILE": 16})
    with pytest.raises(ValueError, match="whole lines"):
        fill("{{BLOCK}}\n", {"BLOCK": "a = 1;"})


def test_read_snippet_reads_the_file_beside_the_package():
    types = read_snippet("mcsplat.compute", "simd_vector_types.h", {"LANES": 8})
    assert "ext_vector_type(8)" in types and "{{" not in types


def test_every_cpp_file_is_read_by_a_module_and_shipped():
    assert CPP_FILES, "the kernels' C++ files are missing"
    sources = "\n".join(p.read_text() for p in PACKAGE.rglob("*.py"))
    unread = [p.name for p in CPP_FILES if f'"{p.name}"' not in sources]
    assert not unread, f"C++ files no module reads: {unread}"
    assert '"**/*.cpp", "**/*.h"' in (ROOT / "pyproject.toml").read_text(), "pyproject.toml must ship the C++ files"
