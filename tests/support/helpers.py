"""Small helpers shared by several test modules."""

from __future__ import annotations

import math
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from PIL import Image
from scipy.spatial.transform import Rotation


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


def perturbed_cup(shared_data: Path, root: Path, train_names: set[str], degrees: float, radius_share: float,
                  scene_radius: float, image_folders: tuple[str, ...] = ("images_4",)) -> dict[str, np.ndarray]:
    """A copy of the cup in `root` with each training image's pose (`train_names`: the loader's view names) moved, in
    its camera's axes, by `degrees` about a random axis and `radius_share` of the scene radius in a random direction
    (the test views untouched); returns each moved image's rotation vector (radians). images.bin is patched in place:
    u64 count, then per image u32 id, f64 qvec[4] (w x y z), f64 tvec[3], u32 camera id, the name + NUL, u64 point
    count and 24 bytes per point."""
    from mcsplat.pose_refinement import correction_matrix

    source = shared_data / "colmap_cup"
    for folder in image_folders:
        shutil.copytree(source / folder, root / folder, copy_function=shutil.copyfile)
    (root / "sparse" / "0").mkdir(parents=True)
    for name in ("cameras.bin", "points3D.bin"):
        shutil.copyfile(source / "sparse" / "0" / name, root / "sparse" / "0" / name)
    data = bytearray((source / "sparse" / "0" / "images.bin").read_bytes())
    rng = np.random.default_rng(0)
    moved, offset = {}, 8
    for _ in range(struct.unpack_from("<Q", data, 0)[0]):
        qvec = np.array(struct.unpack_from("<4d", data, offset + 4))
        tvec = np.array(struct.unpack_from("<3d", data, offset + 36))
        end = data.index(b"\0", offset + 64)
        name = Path(data[offset + 64:end].decode()).stem  # the loader's view name
        if name in train_names:
            axis = rng.normal(size=3)
            omega = axis / np.linalg.norm(axis) * math.radians(degrees)
            direction = rng.normal(size=3)
            shift = direction / np.linalg.norm(direction) * radius_share * scene_radius
            delta = correction_matrix(torch.tensor([*omega, *shift], dtype=torch.float64), 1.0).numpy()
            rotation = _rotation_of(qvec)
            new_rotation = delta[:3, :3] @ rotation
            new_translation = delta[:3, :3] @ tvec + delta[:3, 3]
            struct.pack_into("<4d", data, offset + 4, *_quaternion_of(new_rotation))
            struct.pack_into("<3d", data, offset + 36, *new_translation)
            moved[name] = omega
        points = struct.unpack_from("<Q", data, end + 1)[0]
        offset = end + 1 + 8 + points * 24
    (root / "sparse" / "0" / "images.bin").write_bytes(bytes(data))
    return moved


def _rotation_of(qvec: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(qvec[[1, 2, 3, 0]]).as_matrix()  # COLMAP: w x y z; scipy: x y z w


def _quaternion_of(rotation: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rotation).as_quat()[[3, 0, 1, 2]]


def altered_cup(shared_data: Path, root: Path, alter, every: int = 3) -> tuple[Path, set[str]]:
    """A copy of the cup (its 1/4-size photos) where every `every`-th training photo went through `alter` (float
    pixels [H, W, 3] in 0..255 -> the same), the test views (every 8th photo, the loader's split) untouched.
    Returns the scene folder and the names of the altered photos."""
    source = shared_data / "colmap_cup"
    shutil.copytree(source / "sparse", root / "sparse", copy_function=shutil.copyfile)
    (root / "images_4").mkdir(parents=True)
    photos = sorted((source / "images_4").iterdir(), key=lambda p: p.stem)
    train_photos = [p for i, p in enumerate(photos) if i % 8 != 0]
    altered = {p.stem for p in train_photos[::every]}
    for photo in photos:
        if photo.stem in altered:
            pixels = alter(np.asarray(Image.open(photo).convert("RGB")).astype(np.float64))
            Image.fromarray(np.clip(np.rint(pixels), 0, 255).astype(np.uint8)).save(root / "images_4" / photo.name,
                                                                                   quality=95)
        else:
            shutil.copyfile(photo, root / "images_4" / photo.name)
    return root, altered


REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "data" / "lego_demo"


def demo_photos_scene(root: Path, count: int, split: str = "train") -> tuple[Path, list[dict]]:
    """A transforms.json scene of `count` of the demo's `split` images without their alpha channel (on white): a
    real capture as mcsplat sees one (poses, no points, no alpha), so that `train` would triangulate its points.
    Returns the folder and its frames (file_path "<i>.png", so that a test may list them again)."""
    import json

    meta = json.loads((DEMO / f"transforms_{split}.json").read_text())
    root.mkdir(parents=True, exist_ok=True)
    frames = []
    for i, frame in enumerate(meta["frames"][:count]):
        with Image.open(DEMO / (frame["file_path"].removeprefix("./") + ".png")) as image:
            white = Image.new("RGBA", image.size, (255, 255, 255, 255))
            Image.alpha_composite(white, image.convert("RGBA")).convert("RGB").save(root / f"{i}.png")
        frames.append({"file_path": f"{i}.png", "transform_matrix": frame["transform_matrix"]})
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": meta["camera_angle_x"], "frames": frames}))
    return root, frames


def views_a_term_spoke_on(monkeypatch, term_class: type) -> dict[str, list[bool]]:
    """{training view name: per call, whether the loss term class `term_class` gave a value (not None) there},
    filled as a run calls its terms."""
    given: dict[str, list[bool]] = {}
    call = term_class.__call__

    def recorded(self, ctx):
        value = call(self, ctx)
        given.setdefault(ctx.view.name, []).append(value is not None)
        return value

    monkeypatch.setattr(term_class, "__call__", recorded)
    return given


def median_gaussian_case(splats, camera) -> tuple[tuple, torch.Tensor]:
    """`splats` projected and binned for `camera`, as composite()'s positional inputs (white Gaussians on black), and
    the reference's median Gaussian of each pixel: what a kernel's median_gaussian output must equal."""
    from mcsplat.render.bin.warp_kernels import bin_gaussians
    from mcsplat.render.constants import TILE_SIZE
    from mcsplat.render.project.torch_autograd import project_gaussians
    from mcsplat.render.reference import reference_median_gaussian

    proj = project_gaussians(splats.means, splats.quats, splats.scales, splats.opacities, camera)
    width, height = camera.width, camera.height
    bins = bin_gaussians(proj.tile_min, proj.tile_max, proj.depths, proj.radii, -(-width // TILE_SIZE),
                         -(-height // TILE_SIZE), means2d=proj.means2d, alpha_extent=proj.alpha_extent)
    colors = torch.ones(splats.means.shape[0], 3, dtype=splats.means.dtype, device=splats.means.device)
    background = torch.zeros(3, dtype=splats.means.dtype, device=splats.means.device)
    inputs = (proj.means2d, proj.conics, splats.opacities, colors, proj.depths, background, bins, width, height)
    expected = reference_median_gaussian(proj.means2d, proj.conics, splats.opacities, proj.depths, proj.radii,
                                         proj.tile_min, proj.tile_max, width, height)
    return inputs, expected


def random_adam_step(model, optimizers, seed: int | torch.Generator) -> None:
    """One step of every optimizer on a random linear loss of all the model's parameters: deterministic in `seed`, or
    drawn from a generator that carries on between calls."""
    from mcsplat.gaussians import PARAM_KEYS

    g = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(seed)
    loss = sum((model.params[k] * torch.randn(model.params[k].shape, generator=g)).sum() for k in PARAM_KEYS)
    for opt in optimizers.values():
        opt.zero_grad(set_to_none=True)
    loss.backward()
    for opt in optimizers.values():
        opt.step()


def before_each_step(monkeypatch, action: Callable[[int], None]) -> None:
    """Call action(step) in every training step, before MCMC's refinement (to crash, send a signal, move a clock)."""
    from mcsplat.strategy.mcmc import MCMCStrategy

    original = MCMCStrategy.step_post_optimizer

    def patched(self, step, *args, **kwargs):
        action(step)
        return original(self, step, *args, **kwargs)

    monkeypatch.setattr(MCMCStrategy, "step_post_optimizer", patched)


def crash_at(step_to_fail: int) -> Callable[[int], None]:
    def crash(step: int) -> None:
        if step == step_to_fail:
            raise RuntimeError("simulated crash")
    return crash


def signal_at(step_to_signal: int, signum: signal.Signals) -> Callable[[int], None]:
    """The process sends itself `signum` in that step, as a terminal or a batch scheduler would."""
    def send(step: int) -> None:
        if step == step_to_signal:
            signal.raise_signal(signum)
    return send
