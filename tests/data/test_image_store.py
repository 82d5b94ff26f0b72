"""Loading keeps images as uint8: the 184-image bird scene (275 MiB of pixels) stays well under 1 GB."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

# Read by both scripts below: a /proc/self/status entry (VmRSS, VmHWM) in bytes.
STATUS = """
def status(key):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
"""

SCRIPT = STATUS + """
import sys
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


LAZY_SCRIPT = STATUS + """
import json, os, sys
from pathlib import Path

import numpy as np
import torch, pycolmap, PIL.Image
from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.gaussians import GaussianModel
from mcsplat.train import train
from mcsplat.data import load_scene
before = status("VmRSS")
scene = load_scene(sys.argv[1], test_every=100)
for view in scene.train + scene.test:  # every image decoded once: the cache must evict
    view.image
loaded = status("VmHWM")
# The photos are repeats: points from their poses would mean nothing here.
config = TrainConfig(data=Path(sys.argv[1]), out=Path(sys.argv[2]), steps=10, test_every=100, quiet=True,
                     save_every=0, lpips_net="alex", model=ModelConfig(num_init_points=2000, init="random"))
train(config)
print(json.dumps({"before": before, "loaded": loaded, "peak": status("VmHWM"),
                  "views": len(scene.train) + len(scene.test), "notes": scene.notes}))
"""


def test_memory_does_not_grow_with_the_image_count(shared_data: Path, tmp_path: Path) -> None:
    """160 views made from the 77 real cup photos (800x600: 220 MiB of pixels) loaded, every image read, 10 training
    steps, with a 32 MiB image cache: loading stays within the cache, and the peak is the same with 60 views."""
    import json
    import os

    if not Path("/proc/self/status").exists():
        import pytest
        pytest.skip("needs /proc (Linux) to read the peak resident memory")
    photos = sorted((shared_data / "colmap_cup" / "images").glob("*.jpg"))
    scene = tmp_path / "many"
    (scene / "images").mkdir(parents=True)
    frames = []
    for index in range(160):
        # Each view its own image file (the loader uses a repeated image once): the photo's bytes and, after its end
        # marker where decoders do not look, the view's number.
        photo = photos[index % len(photos)].read_bytes()
        (scene / "images" / f"{index:04d}.jpg").write_bytes(photo + str(index).encode())
        angle = 2 * np.pi * index / 160
        c2w = np.eye(4)  # cameras on a circle looking at the origin (OpenGL convention)
        c2w[:3, 3] = [4 * np.cos(angle), 4 * np.sin(angle), 0.5]
        forward = -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        c2w[:3, :3] = np.stack([right, up, -forward], axis=1)
        frames.append({"file_path": f"images/{index:04d}.jpg", "transform_matrix": c2w.tolist()})
    (scene / "transforms.json").write_text(json.dumps({"camera_angle_x": 1.2, "frames": frames}))

    def peak_growth(views: int) -> int:
        meta = json.loads((scene / "transforms.json").read_text())
        meta["frames"] = frames[:views]
        (scene / "transforms.json").write_text(json.dumps(meta))
        # Few malloc arenas: threads otherwise keep freed memory in arenas of their own, which makes the peak noisy.
        env = dict(os.environ, MCSPLAT_IMAGE_CACHE_MB="32", MALLOC_ARENA_MAX="2")
        result = subprocess.run([sys.executable, "-c", LAZY_SCRIPT, str(scene), str(tmp_path / f"run{views}")],
                                capture_output=True, text=True, timeout=300, env=env)
        assert result.returncode == 0, result.stderr[-3000:]
        report = json.loads(result.stdout.strip().splitlines()[-1])
        assert report["views"] == views and any("decoded on demand" in note for note in report["notes"])
        return report["loaded"] - report["before"], report["peak"] - report["before"]

    (many_loaded, many), (few_loaded, few) = peak_growth(160), peak_growth(60)
    pixels = 160 * 800 * 600 * 3
    print(f"peak RSS growth after loading and reading every image: {many_loaded / 2**20:.0f} MiB with 160 views, "
          f"{few_loaded / 2**20:.0f} MiB with 60; after 10 training steps: {many / 2**20:.0f} MiB and "
          f"{few / 2**20:.0f} MiB ({pixels / 2**20:.0f} MiB of pixels for 160 views)")
    assert many_loaded < 32 * 2**20 + 64 * 2**20  # the cache, decode buffers and prefetches in flight
    assert abs(many_loaded - few_loaded) < 24 * 2**20
    assert many < few + 96 * 2**20  # 100 more views would add 137 MiB if they were all kept
