"""docs/paper.md: each claim with the paper's figures beside ours, from the records of every scale.

The page has hand-written prose (what each result means, why it differs) around generated blocks marked
`<!-- generated: NAME -->` ... `<!-- end: NAME -->`: writing the page replaces what is inside the blocks and keeps
everything else, so the prose survives a new run. A page without a block gets it appended.
"""

from __future__ import annotations

import re
import statistics
from pathlib import Path
from typing import Callable

import _common as C

from . import paper_numbers as P
from .experiments import (NOISE_VARIANTS, REGULARIZER_VARIANTS, SCALES, Comparison, Scale, ablation_reference,
                          comparisons, noise_amount)
from .runner import Records, churn

PAGE = C.REPO / "docs" / "paper.md"
COMMAND = ".venv/bin/python -m benchmarks.paper"


# ---------------------------------------------------------------------------------------------- the figures
class Figures:
    """The records of one scale, averaged over the seeds each run has."""

    def __init__(self, scale: Scale) -> None:
        self.scale = scale
        folder = C.RESULTS / "paper" / scale.name
        self.records = Records(folder)
        for record in self.records.by_name.values():  # records written before the runner measured the churn
            if "dead_per_refine" not in record and (folder / "runs" / record["name"]).is_dir():
                record.update(churn(folder / "runs" / record["name"]))

    def seeds(self, base_name: str) -> list[dict]:
        return [r for r in self.records.by_name.values() if r["base_name"] == base_name]

    def mean(self, base_name: str, key: str, seeds: set[int] | None = None) -> float | None:
        values = [r[key] for r in self.seeds(base_name) if r.get(key) is not None
                  and (seeds is None or r["seed"] in seeds)]
        return statistics.fmean(values) if values else None

    def common_seeds(self, row: Comparison) -> set[int]:
        """The seeds both sides of a comparison have: a mean over more seeds on one side would not be a pair."""
        return ({r["seed"] for r in self.seeds(row.baseline.base_name)} &
                {r["seed"] for r in self.seeds(row.variant.base_name)})

    def pair(self, row: Comparison, key: str = "psnr") -> tuple[float | None, float | None]:
        seeds = self.common_seeds(row)
        return self.mean(row.baseline.base_name, key, seeds), self.mean(row.variant.base_name, key, seeds)

    def delta(self, row: Comparison, key: str = "psnr") -> float | None:
        base, variant = self.pair(row, key)
        return None if base is None or variant is None else variant - base

    def seed_count(self, row: Comparison) -> int:
        return len(self.common_seeds(row))

    def rows(self, claim: str) -> list[Comparison]:
        return [row for row in comparisons(self.scale) if row.claim == claim]

    @property
    def empty(self) -> bool:
        return not self.records.by_name


def _f(value: float | None, spec: str = ".2f", signed: bool = False) -> str:
    if value is None:
        return "-"
    return format(value, ("+" if signed else "") + spec)


def _percent(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"


def _quality(figures: Figures, base_name: str, seeds: set[int] | None = None) -> str:
    psnr, ssim, lpips = (figures.mean(base_name, key, seeds) for key in ("psnr", "ssim", "lpips"))
    return f"{_f(psnr)} / {_f(ssim, '.3f')} / {_f(lpips, '.3f')}" if psnr is not None else "not run"


def _qualities(figures: Figures, row: Comparison) -> tuple[str, str]:
    """Both sides of a comparison over the seeds they share."""
    seeds = figures.common_seeds(row)
    return _quality(figures, row.baseline.base_name, seeds), _quality(figures, row.variant.base_name, seeds)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


# ------------------------------------------------------------------------------------------------ the claims
def same_count(figures: Figures) -> str:
    rows = []
    for row in figures.rows("count"):
        delta = figures.delta(row)
        count = figures.mean(row.baseline.base_name, "num_gaussians")
        width, height = (int(v) for v in figures.scale.scenes[row.baseline.scene].size.split("x"))
        rows.append([row.label, _f(count, ",.0f"), _f(None if count is None else count / (width * height), ".1f"),
                     *_qualities(figures, row), _f(delta, signed=True),
                     _f(figures.mean(row.variant.base_name, "relocated_per_gaussian"), ".1f"),
                     _percent(figures.mean(row.variant.base_name, "dead_per_refine")), str(figures.seed_count(row)),
                     "-" if delta is None else ("MCMC ahead" if delta > 0 else "ADC ahead")])
    ours = _table(["scene, init", "count (ADC's final)", "per training pixel", "ADC PSNR / SSIM / LPIPS",
                   "MCMC PSNR / SSIM / LPIPS", "MCMC - ADC (dB)", "MCMC relocations per Gaussian",
                   "MCMC dead at a refine step", "seeds", "verdict"], rows)
    paper = _table(["dataset (paper)", "3DGS", "MCMC", "MCMC - 3DGS"],
                   [[name, f"{a:.2f}", f"{b:.2f}", f"{b - a:+.2f}"] for name, (a, b) in P.SAME_COUNT.items()])
    return f"{paper}\n\nOurs:\n\n{ours}"


def budget(figures: Figures) -> str:
    rows, trends = [], []
    for scene in figures.scale.real_scenes:
        gaps = []
        scene_rows = [r for r in figures.rows("budget") if r.label.startswith(f"{scene},")]
        full = next(r for r in figures.rows("count") if r.label == f"{scene}, sfm init")
        for row in scene_rows + [full]:
            cap = "ADC's count" if row is full else row.label.split("cap ")[1]
            delta = figures.delta(row)
            if delta is not None:
                gaps.append(delta)
            rows.append([scene, cap, *_qualities(figures, row), _f(delta, signed=True),
                         str(figures.seed_count(row))])
        if len(gaps) == len(scene_rows) + 1:
            ahead = all(g > 0 for g in gaps)
            growing = all(a >= b for a, b in zip(gaps, gaps[1:]))
            listed = ", ".join(_f(g, signed=True) for g in gaps)
            trends.append(f"- {scene}: MCMC ahead at every cap: **{'yes' if ahead else 'no'}**; the gap grows as "
                          f"the cap shrinks: **{'yes' if growing else 'no'}** ({listed} dB, smallest cap first)")
    table = _table(["scene", "cap", "ADC PSNR / SSIM / LPIPS", "MCMC PSNR / SSIM / LPIPS", "MCMC - ADC (dB)", "seeds"],
                   rows)
    text = table + "\n\n" + "\n".join(trends)
    wide = figures.rows("budget-start")
    if wide:
        adc = {r.label: r.baseline for r in figures.rows("budget")}
        rows = [[row.label, _f(figures.mean(adc[row.label].base_name, "psnr")), *(_f(v) for v in figures.pair(row)),
                 _f(figures.delta(row), signed=True)] for row in wide]
        text += ("\n\nMCMC at the small caps starting from Gaussians as wide as ADC's (`--model.init-scale 1.0`, "
                 "3DGS's 1.0 x the nearest-neighbour distance, against MCMC's own 0.1 x):\n\n" +
                 _table(["scene, cap", "ADC", "MCMC (0.1 x)", "MCMC (1.0 x)", "1.0 x - 0.1 x (dB)"], rows))
    return text


def initialisation(figures: Figures) -> str:
    rows = []
    for row in figures.rows("init"):
        scene, strategy = row.label.split(", ")[0], row.baseline.strategy
        cap = row.variant.cap
        cap_text = "unbounded" if cap is None else "ADC's count" if isinstance(cap, str) else C.human(cap)
        rows.append([scene, strategy.upper(), cap_text, *(_f(v) for v in figures.pair(row)),
                     _f(figures.delta(row), signed=True), str(figures.seed_count(row))])
    ours = _table(["scene", "strategy", "cap", "random, 3x extent", "random, 1x extent", "1x - 3x (dB)", "seeds"],
                  rows)
    paper = _table(["strategy (paper, Mip-NeRF 360)", "random, 3x", "random, 1x", "1x - 3x"],
                   [[name.upper(), f"{a:.2f}", f"{b:.2f}", f"{b - a:+.2f}"] for name, (a, b) in P.INIT_EXTENT.items()])
    text = f"{paper}\n\nOurs:\n\n{ours}"
    start = figures.rows("init-start")
    if start:
        rows = []
        for row in start:
            seeds = figures.common_seeds(row)
            reference, wide = figures.pair(row)
            narrow = figures.mean(f"{row.label}-mcmc-random-extent1x", "psnr", seeds)  # the 1x cube at 0.1 x
            rows.append([row.label, _f(reference), _f(narrow), _f(wide), _f(figures.delta(row), signed=True),
                         str(len(seeds))])
        text += ("\n\nMCMC in the 1x cube with its initial Gaussians as wide as in the 3x cube (the same points a "
                 "third as far apart: `--model.init-scale 0.3` against MCMC's own 0.1):\n\n" +
                 _table(["scene", "3x cube", "1x cube", "1x cube, 0.3 x", "1x at 0.3 x - 3x (dB)", "seeds"], rows))
    longer = figures.rows("init-steps")
    if longer:
        scene, cap = longer[0].baseline.scene, C.human(int(longer[0].baseline.cap))
        rows = [[row.label, *(_f(v) for v in figures.pair(row)), _f(figures.delta(row), signed=True),
                 str(figures.seed_count(row))] for row in longer]
        text += (f"\n\nMCMC from random points (3x extent) against SfM points, {scene}, {cap} cap, the step schedules "
                 "fitted to each length:\n\n" +
                 _table(["steps", "SfM init", "random init", "random - SfM (dB)", "seeds"], rows))
    return text


def _ablation(figures: Figures, claim: str, variants, paper: dict) -> str:
    rows = []
    for name in variants:
        cells = [name]
        base_psnr, variant_psnr, where = paper[name]
        if base_psnr is not None and variant_psnr is not None:
            cells.append(f"{variant_psnr - base_psnr:+.2f} ({where})")
        elif name == "no-gate-paper-lambda":
            cells.append(f"PSNR < {P.NOISE_NO_GATE_PAPER_LAMBDA_BELOW:g} ({where.split(':')[0]})")
        else:
            cells.append(where)
        for scene in figures.scale.ablation_scenes:
            row = next((r for r in figures.rows(claim) if r.variant.variant == name and r.variant.scene == scene),
                       None)
            delta = figures.delta(row) if row else None
            psnr = figures.pair(row)[1] if row else None
            seeds = figures.seed_count(row) if row else 0
            cells.append("-" if delta is None else f"{_f(delta, signed=True)} ({_f(psnr)}, {seeds} seed"
                         f"{'s' if seeds != 1 else ''})")
        rows.append(cells)
    header = ["variant", "paper: change in PSNR"] + [f"ours, {s}: change (PSNR)" for s in figures.scale.ablation_scenes]
    return _table(header, rows)


def _reference_line(figures: Figures) -> str:
    scale = figures.scale
    cap = "ADC's count" if scale.ablation_cap is None else f"a {C.human(scale.ablation_cap)} cap"
    parts = []
    for scene in scale.ablation_scenes:
        runs = sorted(figures.seeds(ablation_reference(scale, scene).base_name), key=lambda r: r["seed"])
        seeds = "" if len(runs) < 2 else f" (seeds {', '.join(str(r['seed']) for r in runs)}: " + \
            ", ".join(f"{r['psnr']:.2f}" for r in runs) + ")"
        parts.append(f"{scene} {_f(runs[0]['psnr'] if runs else None)} dB{seeds}")
    return (f"The full method they are compared with (MCMC, random init, {cap}), seed 0: {', '.join(parts)}. Each "
            "row compares the seeds both runs have.")


def noise(figures: Figures) -> str:
    text = _ablation(figures, "noise", NOISE_VARIANTS, P.NOISE) + "\n\n" + _reference_line(figures)
    rows = []
    for row in figures.rows("noise-amount"):
        amount = noise_amount(row.label, figures.scale.steps) / noise_amount("lr", figures.scale.steps)
        rows.append([f"{row.label}, {row.variant.scene}", f"{amount:.2f} x", *(_f(v) for v in figures.pair(row)),
                     _f(figures.delta(row), signed=True), str(figures.seed_count(row))])
    if rows:
        text += ("\n\nEach schedule against the paper's exponential decay giving as much noise over the run "
                 "(lambda_noise scaled by the ratio of the two schedules' mean noise):\n\n" +
                 _table(["schedule, scene", "its noise / the paper's", "the schedule", "the paper's at that amount",
                         "the paper's - the schedule (dB)", "seeds"], rows))
    return text


def regularizers(figures: Figures) -> str:
    adc = ", ".join(f"{s} {_f(figures.mean(f'{s}-adc-random', 'psnr'))} dB" for s in figures.scale.ablation_scenes)
    text = (_ablation(figures, "regularizers", list(REGULARIZER_VARIANTS) + ["with-regs"], P.REGULARIZERS) +
            "\n\n" + _reference_line(figures) + f" The with-regs row is ADC (unbounded) against ADC: {adc}.")
    rows = []
    for row in figures.rows("regularizers-count"):
        with_regs = f"{row.baseline.base_name}-with-regs"
        seeds = figures.common_seeds(row)
        rows.append([row.label, *(_f(figures.mean(name, key, seeds), spec) for name in
                                  (row.baseline.base_name, with_regs, row.variant.base_name)
                                  for key, spec in (("num_gaussians", ",.0f"), ("psnr", ".2f"))),
                     str(len(seeds))])
    if rows:
        text += ("\n\nADC without the regularizers, its densification stopped at the count ADC with them ends with "
                 "(random init):\n\n" + _table(["scene", "ADC count", "ADC PSNR", "with regularizers: count", "PSNR",
                                                   "without, at that count: count", "PSNR", "seeds"], rows))
    return text


def timing(figures: Figures) -> str:
    rows = []
    for row in figures.rows("count"):
        adc_ms, mcmc_ms = figures.pair(row, "ms_per_step")
        if adc_ms is None or mcmc_ms is None:
            continue
        rows.append([row.label, _f(figures.mean(row.baseline.base_name, "num_gaussians"), ",.0f"),
                     _f(figures.mean(row.variant.base_name, "num_gaussians"), ",.0f"), _f(adc_ms, ".1f"),
                     _f(mcmc_ms, ".1f"), _f(mcmc_ms / adc_ms, ".2f")])
    a, b = P.MS_PER_STEP_1M
    same = _table(["scene, init", "ADC final count", "MCMC count", "ADC ms/step", "MCMC ms/step", "MCMC / ADC"], rows)
    reg_rows = []
    for row in figures.rows("time"):
        base_s, weak_s = figures.pair(row, "train_seconds")
        reg_rows.append([row.label.split(",")[0], _f(figures.mean(row.baseline.base_name, "psnr")),
                         _f(figures.mean(row.variant.base_name, "psnr")), _f(base_s, ".0f"), _f(weak_s, ".0f"),
                         "-" if not base_s or weak_s is None else _f(weak_s / base_s, ".2f")])
    (t01, p01), (t001, p001) = P.ROOM_OPACITY_REG[0.01], P.ROOM_OPACITY_REG[0.001]
    reg = _table(["scene (SfM init, ADC's count)", "PSNR at 0.01", "PSNR at 0.001", "train s at 0.01",
                  "train s at 0.001", "time 0.001 / 0.01"], reg_rows)
    frozen = {r["run"]: r for r in C.read_jsonl(figures.records.path.parent / "step_time.jsonl")}
    if frozen:
        reg += ("\n\nThe final models side by side (`python -m benchmarks.paper.step_time RUN ...`: render + loss + "
                "backward on the same training views, the runs in turn view by view, median):\n\n" +
                _table(["run", "Gaussians", "views", "ms", "tile pairs", "Gaussians drawn", "mean opacity",
                        "opacity over 0.5", "median largest axis"],
                       [[r["run"], f"{r['num_gaussians']:,}", str(r["views"]), f"{r['ms_render_backward']:.1f}",
                         _f(r.get("tile_pairs"), ",.0f"), _f(r.get("composited"), ",.0f"),
                         _f(r.get("mean_opacity"), ".3f"), _percent(r.get("opaque_share")),
                         _f(r.get("median_largest_axis"), ".4f")] for r in frozen.values()]))
    return (f"The paper: {b:g} ms (MCMC) against {a:g} ms (3DGS) a step at 1M Gaussians, {b / a:.2f}x; on the room "
            f"scene (SfM init, 1.5M cap) the opacity regulariser at 0.001 took {t001:g} min for {p001} dB, at 0.01 "
            f"{t01:g} min for {p01} dB ({t001 / t01:.2f}x the time); 3DGS {P.ROOM_3DGS[0]:g} min for "
            f"{P.ROOM_3DGS[1]} dB.\n\nOurs, at the same count:\n\n{same}\n\nThe opacity regulariser:\n\n{reg}")


def settings(figures: Figures) -> str:
    s = figures.scale
    rows = [[name, setting.size, f"every {setting.test_stride} of the test views" if setting.test_stride > 1
             else "all test views", "real" if setting.real else "synthetic"] for name, setting in s.scenes.items()]
    machines = sorted({C.machine_line(r["machine"]) for r in figures.records.by_name.values() if r.get("machine")})
    done = len(figures.records.by_name)
    return (f"{s.steps:,} steps (the paper's step schedules multiplied by {s.steps / 30_000:.3g}), random init: "
            f"{s.random_points:,} points in a cube of 3x the camera extent (lego and DTU, object-centric: the "
            f"official [-1.3, 1.3]^3 cube); every 8th image held out (lego: its "
            f"test split); LPIPS with VGG. {done} runs recorded. Machine: {'; '.join(machines) or '-'}.\n\n" +
            _table(["scene", "training size", "scored", "kind"], rows))


SECTIONS: dict[str, Callable[[Figures], str]] = {
    "settings": settings, "same-count": same_count, "budget": budget, "initialisation": initialisation,
    "noise": noise, "regularizers": regularizers, "time": timing}


# ------------------------------------------------------------------------------------------------ the page
def block(name: str, scale: str, body: str) -> str:
    return f"<!-- generated: {name} {scale} -->\n{body}\n<!-- end: {name} {scale} -->"


def render_blocks() -> dict[tuple[str, str], str]:
    out = {}
    for scale_name, scale in SCALES.items():
        figures = Figures(scale)
        for name, section in SECTIONS.items():
            if figures.empty:
                body = f"Not run yet at {scale_name} scale: `{COMMAND} --scale {scale_name}`" + \
                       (" on a machine with a GPU (`--device` is chosen by mcsplat: CUDA when present)."
                        if scale_name == "gpu" else ".")
            else:
                body = section(figures)
            out[(name, scale_name)] = body
    return out


def write_page(path: Path = PAGE) -> Path:
    """Replace the generated blocks of the page (appending the ones it lacks) and keep the rest."""
    text = path.read_text() if path.is_file() else "# The paper's claims, reproduced\n"
    for (name, scale), body in render_blocks().items():
        tag = f"{re.escape(name)} {scale}"
        pattern = re.compile(rf"<!-- generated: {tag} -->.*?<!-- end: {tag} -->", re.S)
        new = block(name, scale, body)
        if pattern.search(text):
            text = pattern.sub(lambda _: new, text)
        else:
            text = text.rstrip("\n") + f"\n\n{new}\n"
    C.write_text(path, text if text.endswith("\n") else text + "\n")
    return path
