"""Every claim of the MCMC paper and of its review, run with mcsplat: `python -m benchmarks.paper --scale cpu|gpu`.

The experiments (experiments.py) are the paper's Table 1 / 5 (same number of Gaussians as 3DGS), its limited-budget
figure, Table 2 (random initialisation in boxes of 1x and 3x the camera extent), the rebuttal's noise ablations,
Table 3's regulariser ablation and the reviewers' training-time question. Each run is one `mcsplat.train.train()`,
kept under benchmarks/results/paper/<scale>/runs/ (git-ignored) and recorded in records.jsonl; a finished run is
never trained again, an interrupted one resumes from its checkpoint. page.py turns the records and the paper's
numbers (paper_numbers.py) into docs/paper.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

# The other benchmark scripts import `_common` as a top-level module (they run as `python benchmarks/x.py`).
_BENCHMARKS = str(Path(__file__).resolve().parents[1])
if _BENCHMARKS not in sys.path:
    sys.path.insert(0, _BENCHMARKS)
