"""What a block's training process is estimated to hold at its peak: a fixed share (Python, torch, the compiled
kernels), a share per Gaussian of its cap (parameters, gradients, Adam's two moments, the step's per-Gaussian buffers)
and a share per pixel of its largest training image (the image, the render, the loss and their gradients).

The figures are measured by benchmarks/block_memory.py (peak resident memory of short CPU runs at two caps and two
image sizes, fitted by least squares; docs/blocks.md). A CUDA run holds the per-Gaussian and per-pixel
shares on the GPU, the fixed share in host memory.
"""

from __future__ import annotations

import math
import re

from ..errors import MCSplatError

# The fit of 2026-11-26 (the cup, caps 20k and 150k at 800x600 and 200x150, default options): most of the share per
# pixel is the final evaluation's LPIPS-VGG (its activations on a whole test image), the rest the decoded images.
FIXED_BYTES = 706 * 2**20
BYTES_PER_GAUSSIAN = 961
BYTES_PER_PIXEL = 2_566
UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "kib": 2**10, "m": 2**20, "mb": 2**20, "mib": 2**20,
         "g": 2**30, "gb": 2**30, "gib": 2**30, "t": 2**40, "tb": 2**40, "tib": 2**40}


def estimated_bytes(cap: int, pixels: int) -> int:
    """The peak memory of a run that holds up to `cap` Gaussians and trains on images of `pixels` pixels."""
    return int(FIXED_BYTES + BYTES_PER_GAUSSIAN * cap + BYTES_PER_PIXEL * pixels)


def gaussians_that_fit(memory: int, pixels: int) -> int:
    """The largest cap whose run fits in `memory` bytes with images of `pixels` pixels (0: none fits)."""
    return max(0, math.floor((memory - FIXED_BYTES - BYTES_PER_PIXEL * pixels) / BYTES_PER_GAUSSIAN))


def parse_bytes(text: str) -> int:
    """'16GiB', '16G', '512 MB', '2.5g' -> bytes (binary units: a G is 2^30 bytes)."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
    if not match or match.group(2).lower() not in UNITS:
        raise MCSplatError(f"--memory {text!r} is not understood: give a size such as 16GiB, 512MiB or 8G")
    value = float(match.group(1)) * UNITS[match.group(2).lower()]
    if value <= 0:
        raise MCSplatError(f"--memory {text!r} must be more than nothing")
    return int(value)


def format_bytes(value: int) -> str:
    """Bytes as a short human figure: 1.5 GiB, 730 MiB."""
    if value >= 2**30:
        return f"{value / 2**30:.1f} GiB"
    return f"{value / 2**20:.0f} MiB"
