"""How far a trained scene's depth is from the dataset's own: lego's test-view depth renders, with and without
`--surface`, for MCMC and ADC at the same steps and cap.

    .venv/bin/python benchmarks/depth_accuracy.py                        # the four arms, 2,000 steps at 200x200
    .venv/bin/python benchmarks/depth_accuracy.py --arms mcmc mcmc-surface --steps 2000
    .venv/bin/python benchmarks/depth_accuracy.py --report               # rebuild results.md from results.jsonl
    .venv/bin/python benchmarks/depth_accuracy.py --picture depth-errors-distortion.png --arms mcmc mcmc-surface
        mcmc-antialiased mcmc-surface-antialiased mcmc-surface-distortion10-antialiased
        mcmc-surface-distortion100-antialiased                           # (one line) with 2DGS's distortion
    .venv/bin/python benchmarks/depth_accuracy.py --arms mcmc-surface-antialiased mcmc-surface-multiview-antialiased
        mcmc-surface-multiview0.1x-antialiased                           # (one line) with PGSR's multi-view term

Each arm trains lego at half size (200x200, `--downscale 2`) for --steps with cap 300k (the paper's cap for the
synthetic scenes) from the default 100,000 random points, into results/depth_accuracy/runs/ (git-ignored). It is
then scored at the full 400x400 on every test view: the dataset's depth (8-bit renders decoded as in
shared/data/nerf_synthetic_lego_400/SOURCE.md: about 0.009 units of noise a pixel, one 8-bit step is 0.031) against
the model's median depth (what the mesh export fuses), its alpha-weighted mean depth and the depth of its composited
planes (render(outputs={"planar_depth"}), what --surface's normal term differentiates), over the pixels where both
see the object (the truth's depth above 0 and the model's alpha at least 0.5). Printed per arm: the median and 90th
percentile of the absolute z error, the share of pixels within 0.02 units, the bias (the median of the signed error:
positive where the model's surface lies behind the truth), the share of the truth's object pixels the model covers,
and the run's test PSNR; a picture of one view's error maps goes to results/depth_accuracy/. The median depth's
errors are also given away from depth edges: over the pixels whose 5x5 window of the truth varies by less than 0.1
units (no outline, no jump between parts), which a model trained at 200x200 and scored at 400x400 cannot place to a
scored pixel; the share of pixels that leaves is printed beside them.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import tyro

import _common as C
from framework import Arm, Common

SURFACE = ["--surface", "--no-surface-mesh"]  # the depth is scored here, not the mesh a --surface run ends with
ARMS = {"mcmc": [], "mcmc-surface": SURFACE, "adc": ["--strategy", "adc"],
        "adc-surface": ["--strategy", "adc", *SURFACE],
        # Not run by default: MCMC without its L1 terms on opacity and scale (is the depth bias theirs?) ...
        "mcmc-no-reg": ["--mcmc.opacity-reg", "0", "--mcmc.scale-reg", "0"],
        # ... and with Mip-Splatting's 2D filter, whose opacity compensation undoes the low-pass widening.
        "mcmc-antialiased": ["--antialiased"], "mcmc-surface-antialiased": [*SURFACE, "--antialiased"],
        # ... and with 2DGS's depth distortion at two weights.
        "mcmc-surface-distortion10-antialiased": [*SURFACE, "--antialiased", "--surface-distortion", "10"],
        "mcmc-surface-distortion100-antialiased": [*SURFACE, "--antialiased", "--surface-distortion", "100"],
        # ... and with PGSR's multi-view geometric consistency, at PGSR's weight and a tenth of it.
        "mcmc-surface-multiview-antialiased": [*SURFACE, "--antialiased", "--surface-multiview", "0.03"],
        "mcmc-surface-multiview0.1x-antialiased": [*SURFACE, "--antialiased", "--surface-multiview", "0.003"],
        # ... and trained at the scored size (400x400; the later --downscale wins), as a diagnosis, not an arm of
        # the schedule: is the depth error a training pixel's?
        "mcmc-surface-antialiased-trained-400": [*SURFACE, "--antialiased", "--downscale", "1"]}
DEFAULT_ARMS = ("mcmc", "mcmc-surface", "adc", "adc-surface")
CAP = 300_000
WITHIN = 0.02        # units of the scene (lego is about 2.5 units across)
EDGE_WINDOW = 5      # pixels: "away from depth edges" where the truth varies by less than EDGE_STEP in this window
EDGE_STEP = 0.1      # units: a jump in the truth's depth (the object's outline counts: the background is 0)
ALPHA_SEEN = 0.5     # the model sees the object where its alpha reaches this
PICTURE_VIEW = 0     # the test view whose error maps are drawn


KEY = ("arm", "steps")


@dataclass(frozen=True)
class Options:
    """Lego's depth against the dataset's own test-view depth renders, arm by arm."""

    arms: tuple[Literal[tuple(ARMS)], ...] = DEFAULT_ARMS
    steps: int = 2000
    picture: str | None = None
    """The error maps' file name (default: depth-errors-STEPS[-ARMS].png)."""
    common: Annotated[Common, tyro.conf.OmitArgPrefixes] = Common()


def arms(options: Options) -> list[Arm]:
    return [Arm(f"{arm}-{options.steps}", {"arm": arm, "steps": options.steps}) for arm in options.arms]


def run(arm: Arm, options: Options, folder: Path) -> dict:
    """Train the arm (a finished run is reused), score its depth, and keep the picture's maps for finish()."""
    lego = C.scene_path("lego", options.common.data_root)
    views = scored_views(lego)
    if not views:
        sys.exit(f"{lego} has no test-view depth maps (r_N_depth_0001.png): see the shared data's SOURCE.md")
    run_dir = train(arm.labels["arm"], lego, options.steps, folder / "runs", C.REPO)
    record, maps = score(run_dir, views)
    np.savez(folder / "runs" / f"{arm.name}-maps.npz", **maps)
    return record


def finish(arms: list[Arm], options: Options, folder: Path) -> None:
    """The error maps of every arm asked for, side by side (when all of them have run)."""
    saved = {arm.labels["arm"]: folder / "runs" / f"{arm.name}-maps.npz" for arm in arms}
    if not all(path.is_file() for path in saved.values()):
        return
    name = "" if tuple(options.arms) == DEFAULT_ARMS else "-" + "-".join(options.arms)
    picture({arm: dict(np.load(path)) for arm, path in saved.items()},
            folder / (options.picture or f"depth-errors-{options.steps}{name}.png"))


def train(arm: str, lego: Path, steps: int, runs: Path, script_root: Path) -> Path:
    run = runs / f"{arm}-{steps}"
    if (run / "metrics.json").exists():
        print(f"{arm}: reusing {run}", flush=True)
        return run
    arguments = [str(lego), "--out", str(run), "--overwrite", "--downscale", "2", "--steps", str(steps),
                 "--cap-max", str(CAP), "--quiet", "--save-every", "0", "--lpips-net", "alex", "--no-save-renders",
                 *ARMS[arm]]
    C.train_with_tree(script_root, arguments, runs / f"{arm}-{steps}.log", "depth_accuracy")
    return run


def scored_views(lego: Path):
    """lego's test views at full size, each with the dataset's depth (z, in the scene's units)."""
    from mcsplat.data import load_scene
    from mcsplat.data.attachments import DepthOptions

    scene = load_scene(lego, attachments=[DepthOptions(depth_encoding="nerf-synthetic")])
    return [view for view in scene.test if "depth" in view.attachments]


@torch.no_grad()
def score(run: Path, views) -> tuple[dict, dict]:
    """The depth errors of one run over the views, and the error maps of the picture's view."""
    from mcsplat.render import render
    from mcsplat.run.trained import load

    trained = load(run, torch.device("cpu"))
    errors = {"median": [], "mean": [], "planar": [], "median_interior": []}
    covered = seen = 0
    maps = {}
    for index, view in enumerate(views):
        truth = view.attachment("depth")[..., 0]
        out = render(trained.model, view.camera, None, trained.sh_degree,
                     outputs={"median_depth", "planar_depth"})
        both = (truth > 0) & (out.alpha >= ALPHA_SEEN)
        seen += int((truth > 0).sum())
        covered += int(both.sum())
        for name, depth in (("median", out.median_depth), ("mean", out.depth), ("planar", out.planar_depth)):
            errors[name].append((depth - truth)[both].numpy())
            if index == PICTURE_VIEW:
                shown = torch.where(both, (depth - truth).abs(), torch.full_like(truth, float("nan")))
                maps[name] = shown[_object_box(truth)].numpy()
        errors["median_interior"].append((out.median_depth - truth)[both & away_from_edges(truth)].numpy())
    record = {"views": len(views), "coverage": covered / max(seen, 1),
              "interior_share": sum(map(len, errors["median_interior"])) / max(covered, 1)}
    for name, parts in errors.items():
        signed = np.concatenate(parts)
        values = np.abs(signed)
        record[f"{name}_depth"] = {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
                                   "within": float((values <= WITHIN).mean()), "bias": float(np.median(signed))}
    metrics = json.loads((run / "metrics.json").read_text())
    record.update(psnr=metrics["psnr"], num_gaussians=metrics["num_gaussians"])
    return record, maps


def away_from_edges(truth: torch.Tensor) -> torch.Tensor:
    """[H, W] bool: the truth's depth varies by less than EDGE_STEP over the EDGE_WINDOW-wide window of the pixel."""
    pool = torch.nn.functional.max_pool2d
    padded = truth[None, None]
    spread = pool(padded, EDGE_WINDOW, 1, EDGE_WINDOW // 2) + pool(-padded, EDGE_WINDOW, 1, EDGE_WINDOW // 2)
    return spread[0, 0] < EDGE_STEP


def _object_box(truth: torch.Tensor, margin: int = 4) -> tuple[slice, slice]:
    """The rows and columns around the pixels where the truth has depth (the picture shows the object, not the page)."""
    rows, columns = torch.nonzero(truth > 0, as_tuple=True)
    height, width = truth.shape
    return (slice(max(0, int(rows.min()) - margin), min(height, int(rows.max()) + margin + 1)),
            slice(max(0, int(columns.min()) - margin), min(width, int(columns.max()) + margin + 1)))


def picture(maps: dict[str, dict], path: Path) -> None:
    plt = C.pyplot()
    arms = list(maps)
    figure, axes = plt.subplots(1, len(arms), figsize=(3.0 * len(arms) + 1.0, 4.2), squeeze=False)
    for axis, arm in zip(axes[0], arms):
        shown = axis.imshow(maps[arm]["median"], cmap="magma", vmin=0.0, vmax=0.1)
        axis.set_title(f"{arm}\n|median depth - truth|", fontsize=9)
        axis.axis("off")
    figure.colorbar(shown, ax=axes[0].tolist(), shrink=0.8, label="units (lego is about 2.5 across)")
    figure.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(figure)


def report(records: list[dict], folder: Path) -> str:
    def depth(key: str, part: str, scale: float = 1.0, spec: str = ".4f"):
        return lambda r: format(r[key][part] * scale, spec)

    def interior(part: str, spec: str, scale: float = 1.0):  # not in the records made before it was measured
        return lambda r: format(r["median_interior_depth"][part] * scale, spec) if "median_interior_depth" in r else "-"

    table = C.markdown_table(records, [
        ("arm", "arm", ""), ("steps", "steps", ","), ("Gaussians", "num_gaussians", ","),
        ("test PSNR", "psnr", ".2f"),
        ("median depth: median error", "", depth("median_depth", "median")),
        ("bias", "", depth("median_depth", "bias")),
        ("p90", "", depth("median_depth", "p90")),
        (f"within {WITHIN}", "", depth("median_depth", "within", 100, ".1f")),
        ("mean depth: median error", "", depth("mean_depth", "median")),
        ("p90 ", "", depth("mean_depth", "p90")),
        (f"within {WITHIN} ", "", depth("mean_depth", "within", 100, ".1f")),
        ("planar depth: median error", "", depth("planar_depth", "median")),
        ("p90  ", "", depth("planar_depth", "p90")),
        (f"within {WITHIN}  ", "", depth("planar_depth", "within", 100, ".1f")),
        ("object covered %", "", lambda r: f"{100 * r['coverage']:.1f}"),
        ("away from edges: median error", "", interior("median", ".4f")),
        ("p90   ", "", interior("p90", ".4f")), (f"within {WITHIN}   ", "", interior("within", ".1f", 100)),
        ("pixels %", "", lambda r: f"{100 * r['interior_share']:.0f}" if "interior_share" in r else "-")])
    return table + ("\n\nErrors in lego's units (about 2.5 across), over the test views' pixels where the truth has "
                    f"depth and the model's alpha is at least {ALPHA_SEEN}; \"within\" in % of those pixels. \"Away "
                    f"from edges\": the median depth over those of the pixels whose {EDGE_WINDOW}x{EDGE_WINDOW} window "
                    f"of the truth varies by less than {EDGE_STEP} units (\"pixels %\": their share).\n")


if __name__ == "__main__":
    import framework
    sys.exit(framework.script("depth_accuracy"))
