"""The benchmark tests import the benchmark modules as the scripts do: top-level, from benchmarks/ on the path."""

from __future__ import annotations

import mcsplat  # noqa: F401  (before torch: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)
import sys
from pathlib import Path

BENCHMARKS = str(Path(__file__).resolve().parents[1])
if BENCHMARKS not in sys.path:
    sys.path.insert(0, BENCHMARKS)
