"""Every Gaussian format `mcsplat export` writes, on one trained run: how large the file is and what a reader gets
back from it, as the test views' PSNR of the decoded Gaussians against the render of the run's exported .ply.

    .venv/bin/python benchmarks/export_formats.py              # trains the demo once (`make demo`'s options), then
                                                               # exports and scores it
    .venv/bin/python benchmarks/export_formats.py --run RUN    # a run trained elsewhere

Each format is exported with the command's defaults (`mcsplat export RUN --format F`: the Gaussians above opacity
0.005) into results/export_formats/runs/<run>-files/ (git-ignored), timed. Then, for each file:

    bytes            its size, and the .ply's size divided by it
    mcsplat          the decoded Gaussians (mcsplat's own reader of the format) rendered by mcsplat on every test
                     view: PSNR against the render of the .ply (the .ply holds the model unquantised: the PSNR
                     measures the format's quantisation alone), and against the ground truth
    splat-transform  the same for the .ply that PlayCanvas's @playcanvas/splat-transform (npm, Node) converts the
                     file to, when it is installed (it does not read .glb); it reads a .spz in the .ply's axes
                     rather than the file's RUB (see io/formats/spz.py), which is turned back before rendering

The renders use the run's background and SH degree (a format without SH, .splat, at degree 0).
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import contextlib
import io
import json
import math
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

import _common as C

SCRIPT = "export_formats"
DEMO_OPTIONS = ["--steps", "3500", "--cap-max", "35000", "--model.num-init-points", "17500"]  # the Makefile's demo
# (row name, --format, --spz-version, file ending)
EXPORTS = [("ply", "ply", 3, ".ply"), ("compressed-ply", "compressed-ply", 3, ".compressed.ply"),
           ("splat", "splat", 3, ".splat"), ("spz v3", "spz", 3, ".v3.spz"), ("spz v4", "spz", 4, ".v4.spz"),
           ("sog", "sog", 3, ".sog"), ("glb", "glb", 3, ".glb")]
SPLAT_TRANSFORM = "@playcanvas/splat-transform"
SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)  # io/formats/common.py


@dataclass(frozen=True)
class Options:
    """Every Gaussian format `mcsplat export` writes, on one trained run."""

    run: Path | None = None
    """A trained run (default: the demo, trained once)."""


def demo_run(folder: Path) -> Path:
    run = folder / "runs" / "demo"
    if not (run / "checkpoint.pt").is_file():
        print(f"training the demo into {run} (about 3 minutes on 2 idle cores)", file=sys.stderr)
        C.train_with_tree(C.REPO, [str(C.REPO / "data" / "lego_demo"), "--out", str(run), "--overwrite",
                                   *DEMO_OPTIONS], folder / "runs" / "demo.log", SCRIPT)
    return run


def export_all(run: Path, files: Path) -> list[dict]:
    from mcsplat.export import ExportOptions, export_run

    rows = []
    for name, format_name, version, ending in EXPORTS:
        path = files / f"point_cloud{ending}"
        started = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):  # the command's own lines
            export_run(run, ExportOptions(format=format_name, out=path, spz_version=version))
        rows.append({"format": name, "reader": format_name, "file": str(path), "bytes": path.stat().st_size,
                     "export_seconds": round(time.perf_counter() - started, 2)})
    return rows


def splat_transform_cli() -> list[str] | None:
    """The command that runs splat-transform (as tests/export/test_gltf.py finds npm packages), None without it."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        return None
    root = Path(subprocess.run(["npm", "root", "-g"], capture_output=True, text=True, timeout=60).stdout.strip())
    cli = root / SPLAT_TRANSFORM / "bin" / "cli.mjs"
    return ["node", str(cli)] if cli.is_file() else None


def through_splat_transform(cli: list[str], row: dict) -> dict[str, np.ndarray] | None:
    from mcsplat.io.ply import read_ply

    if row["reader"] == "glb":
        return None
    from plyfile import PlyData

    out = Path(row["file"] + ".splat-transform.ply")
    subprocess.run([*cli, "--quiet", "--overwrite", row["file"], str(out)], check=True, timeout=600)
    # An alpha of 255 (a compressed .ply's) comes out as opacity +inf, which read_ply refuses: sigmoid(30) is 1 too.
    ply = PlyData.read(str(out), mmap=False)
    ply["vertex"].data["opacity"] = np.clip(ply["vertex"].data["opacity"], -30.0, 30.0)
    ply.write(str(out))
    params = {key: value.numpy() for key, value in read_ply(out).items()}
    if row["reader"] == "spz":  # the file's RUB axes, read as the .ply's: turn them back
        params["means"] = params["means"] * np.array([1, -1, -1], np.float32)
        params["quats"] = params["quats"] * np.array([1, 1, -1, -1], np.float32)
        params["shN"] = params["shN"] * SH_FLIP[:params["shN"].shape[1], None].astype(np.float32)
    return params


def renders(params: dict[str, np.ndarray], views, background, sh_degree: int) -> list[torch.Tensor]:
    from mcsplat.gaussians import GaussianModel
    from mcsplat.render import render

    # An empty array (the SH rest of a .splat) made afresh: numpy gives it strides of 0 that the kernels refuse.
    model = GaussianModel(**{key: torch.from_numpy(np.ascontiguousarray(value)) if value.size else
                             torch.zeros(value.shape) for key, value in params.items()})
    degree = min(sh_degree, model.sh_degree)
    with torch.no_grad():
        return [render(model, view.camera, background, degree).rgb.clamp(0, 1) for view in views]


def mean_psnr(images: list[torch.Tensor], targets: list[torch.Tensor]) -> float:
    from mcsplat.metrics import psnr

    value = float(np.mean([psnr(image, target) for image, target in zip(images, targets)]))
    return None if math.isinf(value) else round(value, 2)  # None: the very same pictures (the .ply against itself)


def psnr_cell(key: str):
    """A table cell: the PSNR, "identical" for the very same pictures, "-" where that reader did not run."""
    return lambda row: ("-" if key not in row else "identical" if row[key] is None else f"{row[key]:.2f}")


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    C.warn_if_busy()
    folder = C.results_dir(SCRIPT)
    run_path = args.run or demo_run(folder)
    files = folder / "runs" / f"{run_path.name}-files"
    files.mkdir(parents=True, exist_ok=True)

    from mcsplat.io.formats import read_gaussians
    from mcsplat.io.ply import read_ply
    from mcsplat.run.trained import load

    run = load(run_path, torch.device("cpu"))
    views, background = run.scene.test, run.background
    rows = export_all(run_path, files)
    reference = renders({k: v.numpy() for k, v in read_ply(rows[0]["file"]).items()}, views, background,
                        run.sh_degree)
    truth = [view.image_float(torch.device("cpu")) for view in views]
    cli = splat_transform_cli()
    for row in rows:
        decoded = read_gaussians(row["reader"], row["file"])
        images = renders(decoded, views, background, run.sh_degree)
        row.update(gaussians=len(decoded["means"]), ratio=round(rows[0]["bytes"] / row["bytes"], 1),
                   psnr_vs_ply=mean_psnr(images, reference), psnr_vs_truth=mean_psnr(images, truth))
        theirs = through_splat_transform(cli, row) if cli else None
        if theirs is not None:
            row["splat_transform_psnr_vs_ply"] = mean_psnr(renders(theirs, views, background, run.sh_degree),
                                                           reference)
        row.update(run=str(run_path), views=len(views), machine=C.machine_line(C.machine()),
                   commit=C.git_commit(), timestamp=C.timestamp())
        C.emit(row)
    C.append_jsonl(folder / "results.jsonl", rows)
    columns = [("format", "format", ""), ("bytes", "bytes", ","), (".ply / it", "ratio", ".1f"),
               ("export s", "export_seconds", ".1f"),
               ("PSNR vs .ply render (mcsplat's reader)", "psnr_vs_ply", psnr_cell("psnr_vs_ply")),
               ("PSNR vs .ply render (splat-transform)", "splat_transform_psnr_vs_ply",
                psnr_cell("splat_transform_psnr_vs_ply")),
               ("test PSNR vs ground truth", "psnr_vs_truth", ".2f")]
    C.write_results_page(folder, f"Export formats of {run_path.name} ({rows[0]['gaussians']:,} Gaussians, "
                                 f"{len(views)} test views)", f"{SCRIPT}.py", rows, columns)
    print(C.markdown_table(rows, columns))
    print(json.dumps({"splat_transform": cli is not None}), file=sys.stderr)


if __name__ == "__main__":
    main()
