"""Meshes of a scene whose surface is known exactly: the Chamfer distance of `mcsplat export RUN --format mesh`
against the true mesh (exact_mesh_scene.py, chamfer.py), plain MCMC against MCMC with --surface.

    .venv/bin/python benchmarks/mesh_chamfer.py                                   # both arms, 3,000 steps
    .venv/bin/python benchmarks/mesh_chamfer.py --arms mcmc-surface --steps 2000
    .venv/bin/python benchmarks/mesh_chamfer.py --arms mcmc-surface --depth planar   # fuse the planar depth
    .venv/bin/python benchmarks/mesh_chamfer.py --arms mcmc --truncation 24         # a wider band
    .venv/bin/python benchmarks/mesh_chamfer.py --arms mcmc --clear-alpha 0.5       # the fusion before the clear depth
    .venv/bin/python benchmarks/mesh_chamfer.py --report                          # rebuild results.md

The scene is written once into results/mesh_chamfer/scene/ (80 training and 20 test views of 200x200 around a
rounded box with a dent, a ball and a ring; git-ignored) and each arm trains on it into results/mesh_chamfer/runs/
(git-ignored; a finished run is reused) with mesh_quality.py's squeezed schedule: 3,000 steps (--steps), cap 100k,
refinement from step 50 every 10 steps to 2,500, SH degree +1 every 100 steps, from the Blender scenes' 100,000
random points. Each run's mesh is exported in a fresh process by `mcsplat export RUN --format mesh` with its defaults
into RUN/chamfer_mesh.ply (not the run's own mesh.ply, whose writing also makes the run's report again, inside the
timing); the arms after the first wait for it and fuse in the voxel size it recorded (`--voxel-size`), so that the
arms are meshed alike; an arm already recorded is not measured again (--rerun measures it again). With `--depth
planar` the export fuses the planar depth instead of the median depth, with `--truncation N` in a band of N voxels
(into RUN/chamfer_mesh-planar.ply, -t24.ply, ...; the arm is recorded as `<arm>-planar`, `<arm>-t24`). Then, in %
of the true mesh's bounding-box diagonal (chamfer.py's docstring has the definitions):

    accuracy       exported surface -> true surface: median, mean, and the share within 1% (precision)
    completeness   true surface -> exported surface: median, mean, and the share within 1% (recall)
    Chamfer        the mean of the two means; F-score, the harmonic mean of the two shares
    offset         the median signed distance exported -> true surface, negative inside the true shape

and a picture per arm (results/mesh_chamfer/<arm>.png): from one test view, the true mesh, the exported mesh, and the
exported mesh coloured by its distance to the truth.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import trimesh
import tyro

import _common as C
from framework import Arm, Common, recorded
from mcsplat.mesh.grid import TRUNCATION_VOXELS
from mcsplat.mesh.options import CLEAR_ALPHA
import chamfer
import exact_mesh_scene as exact
from mesh_quality import STRATEGY_OPTIONS, TRAIN_OPTIONS, reusable
from mesh_quality import export as mesh_quality_export

ARMS = ("mcmc", "mcmc-surface")
PICTURE_SIDE = 360       # pixels of a picture panel's side
PICTURE_FROM = (0.35, 0.75, 0.55)  # the pictures' view: the test camera nearest to this direction from the origin
ERROR_SCALE = 0.02       # the error panel's colours run from 0 to this share of the true diagonal
KEY = ("arm",)


@dataclass(frozen=True)
class Options:
    """Meshes against an exact surface: Chamfer figures of `mcsplat export --format mesh`."""

    arms: tuple[Literal[tuple(STRATEGY_OPTIONS)], ...] = ARMS
    steps: int = 3000
    """Training steps."""
    depth: Literal["median", "planar"] = "median"
    """The depth the export fuses."""
    truncation: float = TRUNCATION_VOXELS
    """The export's band, in voxels."""
    clear_alpha: float = CLEAR_ALPHA
    """The export's MeshOptions.clear_alpha (0.5: the fusion before the clear depth), exported in Python as
    `mcsplat export` does (the command has no such option); the arm is recorded as `<arm>-clear<A>`."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    """An arm per strategy, named with the export's suffix; the later ones wait for the first (its voxel size)."""
    names = [arm + suffix(options.depth, options.truncation, options.clear_alpha) for arm in options.arms]
    return [Arm(name, {"arm": name, "strategy": arm}, after=tuple(names[:1]) if index else ())
            for index, (arm, name) in enumerate(zip(options.arms, names))]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """Train the arm (a finished run is reused), export its mesh, score it against the true mesh."""
    scene_dir = scene(folder / "scene")
    loaded = C.load(scene_dir)
    truth = trimesh.load(scene_dir / "mesh.ply", force="mesh", process=False)
    run_dir = train(arm.labels["strategy"], options.steps, options.common.threads, scene_dir, folder / "runs")
    voxel_size = recorded("mesh_chamfer", folder).get(arm.after[0])["voxel_size"] if arm.after else None
    exported = export(run_dir, voxel_size, options.depth, options.truncation, options.clear_alpha)
    return measure(arm.name, run_dir, exported, truth, loaded, folder / f"{arm.name}.png")


# ------------------------------------------------------------------------------------------------ scene, runs
def scene(folder: Path) -> Path:
    """The scene folder, written first unless a complete one is there (its test transforms are written last)."""
    if not (folder / "transforms_test.json").is_file():
        print(f"writing the scene into {folder}", file=sys.stderr, flush=True)
        try:
            exact.write_scene(folder)
        except exact.SceneError as error:
            sys.exit(f"mesh_chamfer.py: {error}")
    return folder


def options(arm: str, steps: int) -> list[str]:
    """mesh_quality.py's training options for the arm, with `steps` in place of its 3,000."""
    given = list(TRAIN_OPTIONS)
    given[given.index("--steps") + 1] = str(steps)
    return [*given, *STRATEGY_OPTIONS[arm]]


def train(arm: str, steps: int, threads: int | None, scene_dir: Path, runs: Path) -> Path:
    """The arm's run folder under `runs`, trained first unless a finished run is there."""
    run = runs / arm
    if reusable(run):
        return run
    args = [str(scene_dir), "--out", str(run), "--overwrite", *(["--threads", str(threads)] if threads else []),
            "--quiet", *options(arm, steps)]
    print("mcsplat train " + " ".join(args), file=sys.stderr, flush=True)
    C.train_with_tree(C.REPO, args, runs / f"{arm}.log", "mesh_chamfer.py")
    return run


def export(run: Path, voxel_size: float | None, depth: str = "median", truncation: float = TRUNCATION_VOXELS,
           clear_alpha: float = CLEAR_ALPHA) -> dict:
    """`mcsplat export RUN --format mesh` in a fresh process, timed; the mesh goes to RUN/chamfer_mesh<suffix>.ply
    (suffix(): none with the export's defaults). Another clear alpha than the default (no option of the command):
    mesh_quality.py's export worker."""
    out = run / f"chamfer_mesh{suffix(depth, truncation, clear_alpha)}.ply"
    if clear_alpha != CLEAR_ALPHA:
        made = mesh_quality_export(run, voxel_size, truncation, clear_alpha, out, depth)
        return {"mesh_file": out, "export_seconds": made["export_seconds"], "voxel_size": made["voxel_size"]}
    size = [] if voxel_size is None else ["--voxel-size", repr(voxel_size), "--voxel-budget", str(1 << 26)]
    command = [sys.executable, "-m", "mcsplat", "export", str(run), "--format", "mesh", "--out", str(out), *size,
               "--depth", depth, "--truncation", repr(truncation)]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(C.REPO / "src")))
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        sys.exit(f"mesh_chamfer.py: export of {run} failed: {done.stderr.strip().splitlines()[-1:]}")
    said = re.search(r"voxels of ([0-9.e+-]+)", done.stdout)
    return {"mesh_file": out, "export_seconds": round(seconds, 1), "voxel_size": float(said.group(1)) if said else None}


def suffix(depth: str, truncation: float, clear_alpha: float = CLEAR_ALPHA) -> str:
    """-planar for the planar depth, -t<N> for a band of N voxels, -clear<A> for a clear alpha other than the
    defaults, any of them, or none."""
    return (("" if depth == "median" else f"-{depth}")
            + ("" if truncation == TRUNCATION_VOXELS else f"-t{truncation:g}")
            + ("" if clear_alpha == CLEAR_ALPHA else f"-clear{clear_alpha:g}"))


# ------------------------------------------------------------------------------------------------ measures
def measure(arm: str, run: Path, exported: dict, truth: trimesh.Trimesh, loaded, picture_path: Path) -> dict:
    """The run's record: its training figures, the exported mesh's size and its Chamfer figures."""
    from mcsplat.mesh import read_mesh

    mesh = read_mesh(exported["mesh_file"])
    metrics = json.loads((run / "metrics.json").read_text())
    config = json.loads((run / "config.json").read_text())
    figures = chamfer.chamfer(mesh, truth)
    record = {"steps": metrics["steps"], "cap_max": config["cap_max"], "surface": config["surface"],
              "psnr": round(metrics["psnr"], 2), "ssim": round(metrics["ssim"], 4),
              "num_gaussians": metrics["num_gaussians"], "train_seconds": metrics["train_seconds"],
              "export_seconds": exported["export_seconds"], "voxel_size": exported["voxel_size"],
              "vertices": len(mesh.vertices), "faces": len(mesh.faces), "true_faces": len(truth.faces),
              "scene": {"train": len(loaded.train), "test": len(loaded.test), "size": loaded.train[0].camera.width},
              **figures}
    picture(arm, mesh, truth, loaded, figures["diagonal"], picture_path)
    return record


def picture_camera(loaded):
    """The test view nearest to PICTURE_FROM (from the front right and above: it shows the dent, the ball and the
    ring's hole), enlarged to PICTURE_SIDE."""
    towards = torch.nn.functional.normalize(torch.tensor(PICTURE_FROM, dtype=torch.float64), dim=0)

    def alignment(view):
        return float(torch.nn.functional.normalize(view.camera.center.double(), dim=0) @ towards)

    camera = max(loaded.test or loaded.train, key=alignment).camera
    return camera.scaled(PICTURE_SIDE, PICTURE_SIDE)


@torch.no_grad()
def picture(arm: str, mesh: trimesh.Trimesh, truth: trimesh.Trimesh, loaded, unit: float, path: Path) -> None:
    """`path` (results/mesh_chamfer/<arm>.png): the true mesh and the exported one shaded, and the exported one
    coloured by each vertex's distance to the truth, from one test view."""
    from mcsplat.mesh.raster import picture as mesh_picture

    plt = C.pyplot()
    if plt is None:
        return
    camera = picture_camera(loaded)

    def tensors(m):
        return torch.from_numpy(np.asarray(m.vertices, dtype=np.float64)), torch.from_numpy(np.asarray(m.faces))

    off = chamfer.to_surface(np.asarray(mesh.vertices, dtype=np.float64), truth) / unit
    colours = torch.from_numpy(plt.get_cmap("viridis")(np.clip(off / ERROR_SCALE, 0, 1))[:, :3])
    panels = [("true mesh", mesh_picture(*tensors(truth), camera)),
              (f"{arm}: exported", mesh_picture(*tensors(mesh), camera)),
              (f"{arm}: distance to the truth", mesh_picture(*tensors(mesh), camera, colours))]
    figure, axes = plt.subplots(1, 3, figsize=(10.5, 3.9))
    for axis, (title, image) in zip(axes, panels):
        axis.imshow(image)
        axis.set_title(title, fontsize=10)
        axis.axis("off")
    scale = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, 100 * ERROR_SCALE))
    figure.colorbar(scale, ax=axes[2], fraction=0.046, pad=0.02, label="% of the true diagonal")
    figure.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(figure)


# ------------------------------------------------------------------------------------------------ report
def percent(key: str):
    return lambda r: "-" if r.get(key) is None else f"{100 * r[key]:.1f}"


def report(records: list[dict], folder: Path) -> str:
    """results.md: the table of the last record of each arm, and what the truth was."""
    table = C.markdown_table(records, [
        ("arm", "arm", ""), ("steps", "steps", ","), ("PSNR", "psnr", ".2f"), ("Gaussians", "num_gaussians", ","),
        ("train s", "train_seconds", ".0f"), ("faces", "faces", ","),
        ("voxel % diag", "", lambda r: f"{100 * r['voxel_size'] / r['diagonal']:.3f}" if r.get("voxel_size") else "-"),
        ("accuracy median %", "accuracy_median_pct", ".3f"), ("accuracy mean %", "accuracy_mean_pct", ".3f"),
        ("completeness median %", "completeness_median_pct", ".3f"),
        ("completeness mean %", "completeness_mean_pct", ".3f"), ("Chamfer mean %", "chamfer_mean_pct", ".3f"),
        ("offset %", "offset_median_pct", "+.3f"),
        ("accurate within 1% (precision)", "", percent("accuracy_within")),
        ("complete within 1% (recall)", "", percent("completeness_within")), ("F-score", "", percent("f_score")),
        ("export s", "export_seconds", ".0f")])
    first = records[0] if records else {}
    shape = (f"The truth: {first['true_faces']:,} faces, bounding-box diagonal {first['diagonal']:.4f} scene units; "
             f"{first['scene']['train']} training and {first['scene']['test']} test views of "
             f"{first['scene']['size']}x{first['scene']['size']}.") if first else ""
    return (f"# Meshes against an exact surface\n\n`.venv/bin/python benchmarks/mesh_chamfer.py` (the module "
            f"docstring says what each column is).\n\n{table}\n\nDistances in % of the true mesh's bounding-box "
            f"diagonal, from {chamfer.SAMPLES:,} points sampled by area on each surface to the other surface. {shape} "
            "Export: `mcsplat export RUN --format mesh` with its defaults, in a fresh process on the CPU; the "
            "pictures are <arm>.png.\n")


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("mesh_chamfer"))
