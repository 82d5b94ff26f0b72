"""Small helpers shared by several test modules (pytest puts this folder on sys.path)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import torch


def visible_fraction(view, points: torch.Tensor) -> float:
    """Share of `points` that project inside the view's image with positive depth."""
    cam = view.camera
    in_camera = points @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    z = in_camera[:, 2]
    uv = (in_camera @ cam.K.T)[:, :2] / z[:, None]
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return inside.float().mean().item()


def on_a_small_disk(folder: Path, options: str, code: str, *args: str) -> subprocess.CompletedProcess:
    """Run the Python `code` (sys.argv[1:] = args) in a user and mount namespace of its own, in which `folder` is a new
    tmpfs mounted with `options` ("size=3m": a small disk to fill; "ro": a read-only file system); what it printed
    comes back. The way to make a full disk or a read-only file system without root (and without touching the
    machine's own mounts)."""
    folder.mkdir(parents=True, exist_ok=True)
    mount = 'mount -t tmpfs -o "$0" tmpfs "$1" && shift && exec "$@"'
    return subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", mount, options, str(folder),
                           sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600)


def small_disks_work(folder: Path) -> bool:
    """Whether on_a_small_disk can mount here (user namespaces may be switched off)."""
    if shutil.which("unshare") is None:
        return False
    return on_a_small_disk(folder, "size=64k", "pass").returncode == 0
