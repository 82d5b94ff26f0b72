"""Meshes of trained scenes (`mcsplat export --format mesh`): how close they come to geometry nobody here made, and
whether MCMC puts its Gaussians on the surface more than ADC does, at the same cap, steps and fusion settings.

    .venv/bin/python benchmarks/mesh_quality.py                        # cup and bird (MCMC, ADC), DTU and lego (MCMC)
    .venv/bin/python benchmarks/mesh_quality.py --scenes cup --strategies mcmc adc
    .venv/bin/python benchmarks/mesh_quality.py --runs RUN [RUN ...]   # runs trained elsewhere (no SfM: no distances)
    .venv/bin/python benchmarks/mesh_quality.py --report               # rebuild results.md from results.jsonl
    .venv/bin/python benchmarks/mesh_quality.py --scenes bird --strategies mcmc --truncation 24   # a wider band
    .venv/bin/python benchmarks/mesh_quality.py --scenes cup --strategies mcmc --clear-alpha 0.5   # the fusion before

Each scene trains (or a finished run is reused) with the squeezed schedule of the other benchmarks: 3,000 steps, cap
100k, refinement from step 50 every 10 steps to 2,500 (MCMC) or densification to 1,500 with an opacity reset every
300 (ADC), SH degree +1 every 100 steps, images at half size (DTU at full size, from 5,000 random points as in
auto_cap.py; lego from the default 100,000; the captures from their SfM points), into results/mesh_quality/runs/
(git-ignored). Every run's mesh is exported in a fresh process with the command's defaults (voxel budget 2^24,
--alpha-min 0.5, --min-component 0.02), which records its time and peak memory; a scene's later arms wait for its
first one and fuse in the voxel size it recorded, so that MCMC and ADC are meshed alike. A run already recorded is
not measured again (--rerun measures it again). Then, in units of the scene radius R
(3DGS's: 1.1 x the cameras' largest distance from their centre):

    SfM points -> mesh       distance from each COLMAP point (triangulated from image features) to the mesh: median,
                             90th percentile, and the share within 1% of R (completeness)
    mesh -> SfM points       distance from each mesh vertex to the nearest COLMAP point (an accuracy proxy: the points
                             are sparse, so it is never 0)
    Gaussians on the surface the share of the live Gaussians (opacity above 0.005) whose centre lies within 3 voxels of
                             the mesh, plainly and weighted by opacity
    depth agreement          on up to 10 test views, the share of pixels where both show a surface whose mesh depth
                             (mcsplat.mesh.raster) is within 1% of the splats' median depth

and a picture per run: a test view's splats, the mesh in its vertex colours and the mesh shaded
(results/mesh_quality/<run>.png).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import tyro
from scipy.spatial import cKDTree

import _common as C
from framework import Arm, Common, recorded
from mcsplat.mesh.grid import TRUNCATION_VOXELS
from mcsplat.mesh.options import CLEAR_ALPHA

# name -> (folder under the shared data, downscale, options of its own)
SCENES = {"cup": ("colmap_cup", 2, []), "bird": ("colmap_bird", 2, []),
          "dtu": ("dtu_scan24_monosdf/scan24", 1, ["--model.num-init-points", "5000"]), "lego": (C.LEGO, 2, [])}
DEFAULT_JOBS = [("cup", "mcmc"), ("cup", "adc"), ("bird", "mcmc"), ("bird", "adc"), ("dtu", "mcmc"), ("lego", "mcmc")]
# --no-scale-schedule: the schedules below are already squeezed to 3,000 steps; without it the trainer fits them to
# --steps a second time (refinement every step from 5 to 250, ADC's opacity reset every 30 steps, SH every 10 steps),
# which is how the runs of results/mesh_quality and results/mesh_chamfer up to 2026-11-27 were trained.
# A --surface arm does not make its mesh as it ends (--no-surface-mesh): the export below makes every arm's mesh alike,
# in a process of its own that records its time and memory.
TRAIN_OPTIONS = ["--steps", "3000", "--cap-max", "100000", "--sh-increase-every", "100", "--lpips-net", "alex",
                 "--no-save-renders", "--no-scale-schedule"]
STRATEGY_OPTIONS = {
    "mcmc": ["--mcmc.refine-start", "50", "--mcmc.refine-every", "10", "--mcmc.refine-stop", "2500"],
    "mcmc-surface": ["--mcmc.refine-start", "50", "--mcmc.refine-every", "10", "--mcmc.refine-stop", "2500",
                     "--surface", "--no-surface-mesh"],
    "adc": ["--strategy", "adc", "--adc.densify-start", "50", "--adc.densify-every", "10", "--adc.densify-stop",
            "1500", "--adc.reset-every", "300"]}
# With Mip-Splatting's 2D filter, which removes the inward bias of 3DGS's low-pass widening (depth_accuracy.py).
STRATEGY_OPTIONS["mcmc-antialiased"] = STRATEGY_OPTIONS["mcmc"] + ["--antialiased"]
STRATEGY_OPTIONS["mcmc-surface-antialiased"] = STRATEGY_OPTIONS["mcmc-surface"] + ["--antialiased"]
STRATEGY_OPTIONS["adc-surface"] = STRATEGY_OPTIONS["adc"] + ["--surface", "--no-surface-mesh"]
# --surface's normal term from half way instead of 0.23 of the run (its PSNR cost, issue 59)
STRATEGY_OPTIONS["mcmc-surface-late"] = STRATEGY_OPTIONS["mcmc-surface"] + ["--surface-from", "0.5"]
# ... and with the flattening at a tenth of PGSR's weight, or off: whether it is the flattening that costs the PSNR
STRATEGY_OPTIONS["mcmc-surface-flatten10"] = STRATEGY_OPTIONS["mcmc-surface"] + ["--surface-flatten", "10"]
STRATEGY_OPTIONS["mcmc-surface-flatten0"] = STRATEGY_OPTIONS["mcmc-surface"] + ["--surface-flatten", "0"]
# ... and with the depth-normal term at a third of PGSR's weight
STRATEGY_OPTIONS["mcmc-surface-normal005"] = STRATEGY_OPTIONS["mcmc-surface"] + ["--surface-normal", "0.005"]
# The same three with another seed: how far single runs of this schedule differ
for _arm in ("mcmc", "mcmc-surface", "mcmc-surface-normal005"):
    STRATEGY_OPTIONS[f"{_arm}-seed1"] = STRATEGY_OPTIONS[_arm] + ["--seed", "1"]
# Depth supervision from the SfM points each image saw, from the first step (COLMAP scenes only: cup and bird)
SPARSE_DEPTH = ["--sparse-depth", "0.1", "--sparse-depth-from", "0", "--sparse-depth-final", "1"]  # held to the end
STRATEGY_OPTIONS["mcmc-sparse-depth"] = STRATEGY_OPTIONS["mcmc"] + SPARSE_DEPTH
STRATEGY_OPTIONS["mcmc-surface-sparse-depth"] = STRATEGY_OPTIONS["mcmc-surface"] + SPARSE_DEPTH
NEAR_VOXELS = 3           # "on the surface": within this many voxels of the mesh
COMPLETE = 0.01           # completeness threshold, in units of R
AGREEMENT = 0.01          # depth agreement threshold, relative to the depth
AGREEMENT_VIEWS = 10
PICTURE_SIDE = 320        # pixels of a picture panel's longest side
KEY = ("run",)


@dataclass(frozen=True)
class Options:
    """Meshes of trained scenes against the SfM points, MCMC against ADC."""

    scenes: tuple[Literal[tuple(SCENES)], ...] | None = None
    """Default: cup, bird, dtu, lego."""
    strategies: tuple[Literal[tuple(STRATEGY_OPTIONS)], ...] | None = None
    """Default: MCMC and ADC on cup and bird, MCMC on dtu and lego (with --scenes too: every strategy on each)."""
    runs: tuple[Path, ...] = ()
    """Measure these run folders instead of training."""
    truncation: float = TRUNCATION_VOXELS
    """The export's --truncation, in voxels; the runs' records and pictures are then named <run>-t<N>."""
    clear_alpha: float = CLEAR_ALPHA
    """The export's MeshOptions.clear_alpha (0.5: each view vouches for empty space in front of its median depth, as
    before 2026-11-29); the records and pictures are then named <run>-clear<A>."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def trained_runs(options: Options) -> list[tuple[str, str]]:
    """The (scene, strategy) pairs to train and measure."""
    if options.scenes and options.strategies:
        return [(scene, strategy) for scene in options.scenes for strategy in options.strategies]
    return [(scene, strategy) for scene, strategy in DEFAULT_JOBS if (options.scenes is None or scene in options.scenes)
            and (options.strategies is None or strategy in options.strategies)]


def export_suffix(options: Options) -> str:
    """-t<N> for an export band of N voxels, -clear<A> for a clear alpha A, where they are not the defaults."""
    return ("" if options.truncation == TRUNCATION_VOXELS else f"-t{options.truncation:g}") + \
        ("" if options.clear_alpha == CLEAR_ALPHA else f"-clear{options.clear_alpha:g}")


def arms(options: Options) -> list[Arm]:
    """An arm per run (<scene>-<strategy>), each after its scene's first arm: it fuses in that one's voxel size."""
    runs = [(run.name, str(run)) for run in options.runs] or [(f"{s}-{k}", None) for s, k in trained_runs(options)]
    first: dict[str, str] = {}  # scene (names have no dash; strategies may) -> its first arm
    declared = []
    for run_name, given in runs:
        name, scene = run_name + export_suffix(options), run_name.split("-", 1)[0]
        labels = {"run": name, "truncation_voxels": options.truncation, "clear_alpha": options.clear_alpha,
                  **({"run_folder": given} if given else {})}
        declared.append(Arm(name, labels, after=(first[scene],) if scene in first else ()))
        first.setdefault(scene, name)
    return declared


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """Train the arm's run (a finished one is reused) or take the one given, export its mesh and measure it."""
    given = arm.labels.get("run_folder")
    trained = arm.name.removesuffix(export_suffix(options))
    run_dir = Path(given) if given else train(*trained.split("-", 1), folder / "runs", options.common.data_root,
                                               options.common.threads)
    voxel_size = recorded("mesh_quality", folder).get(arm.after[0])["voxel_size"] if arm.after else None
    exported = export(run_dir, voxel_size, options.truncation, options.clear_alpha)
    return measure(run_dir, exported, arm.name, folder / f"{arm.name}.png")


# ------------------------------------------------------------------------------------------------ training
def reusable(run: Path) -> bool:
    """A finished run trained on the schedules as written (not one fitted to --steps a second time). A run started
    again writes its config.json at once and its metrics.json only when it finishes, so a metrics.json older than
    the config.json is an earlier run's, left by one that was stopped."""
    config, metrics = run / "config.json", run / "metrics.json"
    return (metrics.is_file() and config.is_file() and metrics.stat().st_mtime >= config.stat().st_mtime
            and json.loads(config.read_text()).get("scale_schedule") is False)


def train(scene: str, strategy: str, runs: Path, data_root: Path, threads: int | None) -> Path:
    """The run folder of (scene, strategy) under `runs`, trained first unless a finished run is there."""
    folder, downscale, own_options = SCENES[scene]
    run = runs / f"{scene}-{strategy}"
    if reusable(run):
        return run
    command = [sys.executable, "-m", "mcsplat", "train", str(data_root / folder), "--out", str(run), "--overwrite",
               "--downscale", str(downscale), *(["--threads", str(threads)] if threads else []), "--quiet",
               *TRAIN_OPTIONS, *STRATEGY_OPTIONS[strategy], *own_options]
    print(" ".join(command[1:]), file=sys.stderr, flush=True)
    subprocess.run(command, check=True, stdout=sys.stderr)  # stdout carries the arm's answer
    return run


# ------------------------------------------------------------------------------------------------ export
def export_worker(run: str, voxel_size: float | None, truncation: float, clear_alpha: float = CLEAR_ALPHA,
                  out: str | None = None, depth: str = "median") -> None:
    """In a fresh process: what `mcsplat export RUN --format mesh [--voxel-size S] [--out OUT] [--depth D]` does,
    with MeshOptions.clear_alpha (no option of the command), timed; prints one JSON line."""
    from mcsplat.run import trained as trained_run
    from mcsplat.mesh import DEFAULT_VOXEL_BUDGET, MeshOptions, extract, write_mesh

    started = time.perf_counter()
    trained = trained_run.load(run, torch.device("cpu"))
    # A given voxel size may need more voxels than the default budget when this model's box is larger.
    size = {} if voxel_size is None else {"voxel_size": voxel_size, "voxel_budget": 4 * DEFAULT_VOXEL_BUDGET}
    options = MeshOptions(**size, truncation=truncation, clear_alpha=clear_alpha, depth=depth)
    mesh = extract(trained.model, trained.scene.train, options, sh_degree=trained.sh_degree)
    write_mesh(Path(out) if out else trained.folder.mesh_file, mesh)
    made = mesh.metadata["mcsplat"]
    grid = made["grid"]
    print(json.dumps({"export_seconds": round(time.perf_counter() - started, 1), "peak_rss_mb": round(C.peak_rss_mb()),
                      "stage_seconds": {k: round(v, 1) for k, v in made["seconds"].items()},
                      "voxel_size": grid.voxel_size, "grid": list(grid.shape), "voxels": grid.num_voxels,
                      "views": made["views"], "vertices": len(mesh.vertices), "faces": len(mesh.faces)}))


def export(run: Path, voxel_size: float | None = None, truncation: float = TRUNCATION_VOXELS,
           clear_alpha: float = CLEAR_ALPHA, out: Path | None = None, depth: str = "median") -> dict:
    """The export worker's figures for `run`, fused in `voxel_size` where that fits 4x the default voxel budget, else
    (a model whose box is much larger: ADC's floaters) in the finest size its own box allows, as the voxel column
    then shows."""
    asked = {"run": str(run), "voxel_size": voxel_size, "truncation": truncation, "clear_alpha": clear_alpha,
             "out": None if out is None else str(out), "depth": depth}
    done = subprocess.run([sys.executable, __file__, "--export-worker", json.dumps(asked)], capture_output=True,
                          text=True)
    if done.returncode != 0 and voxel_size is not None and "over the budget" in done.stderr:
        print(f"{run.name}: the shared voxel size does not fit its box; fused in its own", file=sys.stderr)
        return export(run, None, truncation, clear_alpha, out, depth)
    if done.returncode != 0:
        sys.exit(f"export of {run} failed: {done.stderr.strip()}")
    return json.loads(done.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------------------ distances
def closest_on_triangles(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """[P, 3] closest points of triangles (a, b, c) [P, 3] each to `points` (Ericson, Real-Time Collision
    Detection 5.1.5: the vertex, edge or face region the point projects into)."""
    ab, ac, ap = b - a, c - a, points - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = points - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = points - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denominator = va + vb + vc
        v, w = vb / denominator, vc / denominator
        result = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        t_ab, t_ac = d1 / (d1 - d3), d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [  # later regions take precedence where two conditions hold (the order of Ericson's early exits)
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * np.nan_to_num(t_bc)[:, None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * np.nan_to_num(t_ac)[:, None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * np.nan_to_num(t_ab)[:, None]),
        ((d3 >= 0) & (d4 <= d3), b), ((d1 <= 0) & (d2 <= 0), a)]
    for mask, closest in regions:
        result[mask] = closest[mask]
    return result


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, candidates: int = 16
                     ) -> np.ndarray:
    """[P] distance from each point to the nearest of the `candidates` triangles whose centroids are nearest (exact
    for a mesh of small, even triangles such as marching cubes makes)."""
    triangles = vertices[faces]
    _, nearest = cKDTree(triangles.mean(axis=1)).query(points, k=candidates)
    best = np.full(len(points), np.inf)
    for k in range(candidates):
        t = triangles[nearest[:, k]]
        best = np.minimum(best, np.linalg.norm(points - closest_on_triangles(points, t[:, 0], t[:, 1], t[:, 2]),
                                               axis=1))
    return best


# ------------------------------------------------------------------------------------------------ measures
def measure(run: Path, exported: dict, name: str, picture_path: Path) -> dict:
    from mcsplat.run import trained as trained_run
    from mcsplat.gaussians import DEAD_OPACITY
    from mcsplat.mesh import read_mesh

    trained = trained_run.load(run, torch.device("cpu"))
    mesh = read_mesh(trained.folder.mesh_file)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    scene, radius = trained.scene, trained.scene.radius
    metrics = json.loads((run / "metrics.json").read_text())
    record = {"run": name, "scene": trained.config.data.name, "strategy": trained.config.strategy,
              "psnr": round(metrics["psnr"], 2), "num_gaussians": trained.model.num_gaussians, "radius": radius,
              **exported, "voxel_size_r": exported["voxel_size"] / radius}
    if scene.points is not None:
        points = scene.points.double().numpy()
        to_mesh = distance_to_mesh(points, vertices, faces) / radius
        to_points = cKDTree(points).query(vertices)[0] / radius
        record.update(sfm_points=len(points), points_to_mesh_median=float(np.median(to_mesh)),
                      points_to_mesh_p90=float(np.quantile(to_mesh, 0.9)),
                      completeness=float((to_mesh <= COMPLETE).mean()),
                      mesh_to_points_median=float(np.median(to_points)),
                      mesh_to_points_p90=float(np.quantile(to_points, 0.9)))
    opacities = trained.model.opacities.detach().numpy()
    alive = opacities > DEAD_OPACITY
    near = distance_to_mesh(trained.model.means.detach().double().numpy()[alive], vertices, faces) \
        <= NEAR_VOXELS * exported["voxel_size"]
    record.update(gaussians_on_surface=float(near.mean()),
                  gaussians_on_surface_weighted=float((near * opacities[alive]).sum() / opacities[alive].sum()))
    record.update(depth_agreement(trained, vertices, faces))
    picture(trained, vertices, faces, np.asarray(mesh.visual.vertex_colors)[:, :3], picture_path)
    return record


@torch.no_grad()
def depth_agreement(trained, vertices: np.ndarray, faces: np.ndarray) -> dict:
    from mcsplat.mesh.raster import rasterize
    from mcsplat.render import render

    views = (trained.scene.test or trained.scene.train)[:AGREEMENT_VIEWS]
    v, f = torch.from_numpy(vertices).float(), torch.from_numpy(faces)
    agreeing = covered = surface = 0
    for view in views:
        splats = render(trained.model, view.camera, None, trained.sh_degree, outputs={"median_depth"})
        drawn = rasterize(v, f, view.camera).depth
        shown = splats.alpha >= 0.5
        both = shown & torch.isfinite(drawn)
        difference = (drawn - splats.median_depth).abs() / splats.median_depth
        agreeing += int((difference[both] <= AGREEMENT).sum())
        covered += int(both.sum())
        surface += int(shown.sum())
    return {"depth_agreement": agreeing / max(covered, 1), "mesh_covers": covered / max(surface, 1)}


@torch.no_grad()
def picture(trained, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, path: Path) -> None:
    """One test view: splats, mesh in vertex colours, mesh shaded, side by side."""
    from PIL import Image

    from mcsplat.mesh.raster import picture as mesh_picture
    from mcsplat.render import render

    views = trained.scene.test or trained.scene.train
    camera = views[len(views) // 2].camera
    shrink = min(1.0, PICTURE_SIDE / max(camera.width, camera.height))
    camera = camera.scaled(round(camera.width * shrink), round(camera.height * shrink))
    splats = render(trained.model, camera, trained.background, trained.sh_degree).rgb
    v, f, c = torch.from_numpy(vertices).float(), torch.from_numpy(faces), torch.from_numpy(colors.copy())
    panels = [(splats.clamp(0, 1) * 255 + 0.5).byte().numpy(), mesh_picture(v, f, camera, c),
              mesh_picture(v, f, camera)]
    Image.fromarray(np.concatenate(panels, axis=1)).save(path, optimize=True)


# ------------------------------------------------------------------------------------------------ report
def percent(key: str):
    return lambda r: "-" if r.get(key) is None else f"{100 * r[key]:.2f}"


def arm_of(record: dict) -> str:
    """The record's arm: its run's name after the scene's (mcmc, mcmc-surface, adc, mcmc-t24, ...)."""
    return record["run"].split("-", 1)[1]


def report(records: list[dict], folder: Path) -> str:
    scenes, arms = list(dict.fromkeys(r["scene"] for r in records)), list(STRATEGY_OPTIONS)
    records = sorted(records, key=lambda r: (scenes.index(r["scene"]),
                                             arms.index(arm_of(r)) if arm_of(r) in arms else len(arms)))
    table = C.markdown_table(records, [
        ("run", "run", ""), ("PSNR", "psnr", ".2f"), ("Gaussians", "num_gaussians", ","), ("faces", "faces", ","),
        ("voxel %R", "voxel_size_r", percent("voxel_size_r")),
        ("band (voxels)", "", lambda r: f"{r.get('truncation_voxels', TRUNCATION_VOXELS):g}"),
        # Records before the clear depth (2026-11-29) fused every view's empty space up to its median depth (0.5).
        ("clear alpha", "", lambda r: f"{r.get('clear_alpha', 0.5):g}"),
        ("SfM->mesh median %R", "", percent("points_to_mesh_median")),
        ("SfM->mesh p90 %R", "", percent("points_to_mesh_p90")),
        ("complete (1% R)", "", percent("completeness")),
        ("mesh->SfM median %R", "", percent("mesh_to_points_median")),
        ("mesh->SfM p90 %R", "", percent("mesh_to_points_p90")),
        ("Gaussians on surface %", "", percent("gaussians_on_surface")),
        ("opacity-weighted %", "", percent("gaussians_on_surface_weighted")),
        ("depth within 1% (test views)", "", percent("depth_agreement")),
        ("export s", "export_seconds", ".0f"), ("peak RSS MB", "peak_rss_mb", ",")])
    lines = []
    for scene in dict.fromkeys(r["scene"] for r in records):
        by = {arm_of(r): r for r in records if r["scene"] == scene and "points_to_mesh_median" in r}
        for mcmc, adc in (("mcmc", "adc"), ("mcmc-surface", "adc-surface")):
            if {mcmc, adc} <= set(by):
                m, a = by[mcmc], by[adc]
                if m.get("clear_alpha", 0.5) != a.get("clear_alpha", 0.5):  # fused differently: no comparison
                    continue
                closer = mcmc if m["points_to_mesh_median"] < a["points_to_mesh_median"] else adc
                lines.append(f"- {scene}: {closer}'s mesh is closer to the SfM points (median "
                             f"{100 * m['points_to_mesh_median']:.2f}% R for {mcmc}, "
                             f"{100 * a['points_to_mesh_median']:.2f}% R for {adc}; completeness "
                             f"{100 * m['completeness']:.1f}% vs {100 * a['completeness']:.1f}%); "
                             f"{100 * m['gaussians_on_surface']:.1f}% of {mcmc}'s Gaussians lie within {NEAR_VOXELS} "
                             f"voxels of the surface, {100 * a['gaussians_on_surface']:.1f}% of {adc}'s")
    return (f"# Meshes of trained scenes\n\n{table}\n\n" + "\n".join(lines) + ("\n" if lines else "") +
            f"\nDistances in % of the scene radius R; \"on surface\": the centre within {NEAR_VOXELS} voxels of the "
            f"mesh. Export: `mcsplat export RUN --format mesh` with its defaults, in a fresh process on the CPU.\n")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--export-worker"]:  # export()'s fresh process
        sys.exit(export_worker(**json.loads(sys.argv[2])))
    import framework
    sys.exit(framework.script("mesh_quality"))
