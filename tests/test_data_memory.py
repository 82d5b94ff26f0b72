"""Loading keeps images as uint8: the 184-image bird scene (275 MiB of pixels) stays well under 1 GB."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = """
import sys
def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
import torch, pycolmap, PIL.Image
from mcsplat.data import load_scene
before = status("VmRSS")
scene = load_scene(sys.argv[1])
pixels = sum(v.image.numel() for v in scene.train + scene.test)
print(before, status("VmHWM"), pixels)
"""


def test_bird_memory(shared_data: Path) -> None:
    if not Path("/proc/self/status").exists():
        import pytest
        pytest.skip("needs /proc (Linux) to read the peak resident memory")
    result = subprocess.run([sys.executable, "-c", SCRIPT, str(shared_data / "colmap_bird")], capture_output=True,
                            text=True, timeout=300, check=True)
    before, peak, pixels = map(int, result.stdout.split())
    assert pixels == 184 * 544 * 960 * 3
    growth = peak - before
    print(f"bird: peak RSS grew by {growth / 2**20:.0f} MiB for {pixels / 2**20:.0f} MiB of pixels")
    assert growth < 1.6 * pixels  # the uint8 images plus transient decode buffers, nothing like float32 copies
    assert peak < 1024**3
