"""C++ snippets for SIMD kernels over clang vector types (`wp.func_native`), one item per lane of a LANES-wide vector.

The CPU's SIMD kernels over items (render/project/cpu_simd.py, geometry/covariance.py) take them in chunks of LANES:
chunk c holds items [LANES c, LANES (c + 1)) and a short last chunk repeats its last item in the spare lanes. Their
per-item arrays are interleaved rows (x, y, z of one item, then the next), which lanes_in turns into one vector per
component and lanes_out back: for a full chunk with whole-vector loads or stores and one shuffle per vector (clang
picks the permutes), for a short one lane by lane. The snippets expect `first` (the chunk's first item) and `count`
(its items) in scope, and VECTOR_TYPES's typedefs (simd_vector_types.h).
"""

from __future__ import annotations

import os

from .cpp_snippets import read_snippet

# 16 on every CPU: built for AVX2 (a 16-lane vector is two 256-bit registers), 8 lanes measured no faster
# (benchmarks/README.md, "The CPU kernels built for AVX2", 2026-11-28). MCSPLAT_SIMD_LANES (4, 8 or 16) sets another
# width, to measure it again.
LANES = int(os.environ.get("MCSPLAT_SIMD_LANES", "16"))
assert LANES in (4, 8, 16), "MCSPLAT_SIMD_LANES must be 4, 8 or 16"

# vf / vi: LANES floats / ints; the _u variants allow unaligned loads and stores (rows start anywhere).
VECTOR_TYPES = read_snippet(__package__, "simd_vector_types.h", {"LANES": LANES})
# exp_lanes and log_lanes over a vf (simd_math.h), for kernels that have defined vf and vi.
SIMD_MATH = read_snippet(__package__, "simd_math.h")


def concatenated(parts: list[str]) -> str:
    """C++ for the vectors `parts` (LANES lanes each, at most four) as one vector of LANES x len(parts) lanes, padded
    to 2 or 4 x LANES."""
    if len(parts) == 1:
        return parts[0]
    pairs = [(parts[k], parts[min(k + 1, len(parts) - 1)]) for k in range(0, len(parts), 2)]
    halves = [f"__builtin_shufflevector({a}, {b}, {', '.join(map(str, range(2 * LANES)))})" for a, b in pairs]
    if len(halves) == 1:
        return halves[0]
    return f"__builtin_shufflevector({halves[0]}, {halves[1]}, {', '.join(map(str, range(4 * LANES)))})"


def lanes_in(dst: str, src: str, stride: int, kind: str = "f") -> str:
    """C++ that fills the vectors dst[0 .. stride - 1] with the chunk's rows of an interleaved array (dst[k] lane l
    = src[stride * (first + l) + k]): a full chunk as `stride` vector loads and one shuffle per vector, a short one
    lane by lane (spare lanes repeat the last item)."""
    lanes = LANES
    loads = ", ".join(f"*(const v{kind}_u*)(row + {lanes * k})" for k in range(stride))
    picks = "\n".join(
        f"        {dst}[{k}] = __builtin_shufflevector(all, all, "
        + ", ".join(str(stride * j + k) for j in range(lanes)) + ");" for k in range(stride))
    return f"""
    if (count == {lanes}) {{
        const auto* row = {src} + {stride} * first;
        const v{kind}_u parts[{stride}] = {{{loads}}};
        const auto all = {concatenated([f"(v{kind})parts[{k}]" for k in range(stride)])};
{picks}
    }} else {{
        for (int l = 0; l < {lanes}; ++l) {{
            const int i = first + (l < count ? l : count - 1);
            for (int k = 0; k < {stride}; ++k) {dst}[k][l] = {src}[{stride} * i + k];
        }}
    }}
"""


def lanes_out(values: list[str], dst: str, kind: str = "f", row: str = "first") -> str:
    """C++ that writes the vectors `values` (one per component) as the chunk's rows of an interleaved array
    (dst[stride * (row + l) + k] = values[k] lane l; `row`, the row of the chunk's first item, is `first` unless the
    array holds only some rows): a full chunk as one shuffle and one vector store per 16 entries, a short one lane by
    lane."""
    lanes, stride = LANES, len(values)
    stores = "\n".join(
        f"        *(v{kind}_u*)(row + {lanes * m}) = __builtin_shufflevector(all, all, "
        + ", ".join(str(lanes * (e % stride) + e // stride) for e in range(lanes * m, lanes * (m + 1))) + ");"
        for m in range(stride))
    singles = " ".join(f"{dst}[{stride} * i + {k}] = ({values[k]})[l];" for k in range(stride))
    return f"""
    {{
        if (count == {lanes}) {{
            auto* row = {dst} + {stride} * ({row});
            const auto all = {concatenated([f"(v{kind})({v})" for v in values])};
{stores}
        }} else {{
            for (int l = 0; l < count; ++l) {{
                const int i = ({row}) + l;
                {singles}
            }}
        }}
    }}
"""
