"""The benchmark tests import the benchmark modules as the scripts do: top-level, from benchmarks/ on the path. The
package's own tests' fixtures that these use come from tests/conftest.py (the repository's root on the path)."""

from __future__ import annotations

import mcsplat  # noqa: F401  (before torch: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1]
for folder in (str(BENCHMARKS), str(BENCHMARKS.parent)):
    if folder not in sys.path:
        sys.path.insert(0, folder)

from tests.conftest import shared_data  # noqa: E402, F401
