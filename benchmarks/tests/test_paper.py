"""benchmarks/paper (the paper's claims as runs): every comparison has its runs, every run that takes another's count
comes after it, the seeds of a comparison are paired, and the page keeps its prose when its tables are rewritten."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # `benchmarks` as a package, as `python -m benchmarks.paper` imports it

from benchmarks.paper import experiments, page  # noqa: E402
from benchmarks.paper.__main__ import extra_seed_runs  # noqa: E402
from benchmarks.paper.runner import NotReady, Records, check_options, churn, resolve_cap  # noqa: E402


@pytest.mark.parametrize("scale", sorted(experiments.SCALES))
def test_every_comparison_has_its_runs_and_counts_come_first(scale):
    settings = experiments.SCALES[scale]
    runs = experiments.runs(settings)
    names = [run.name for run in runs]
    assert len(names) == len(set(names))
    position = {name: i for i, name in enumerate(names)}
    for run in runs:
        check_options(run)  # every option exists in this checkout
        if isinstance(run.cap, str):
            assert position[run.cap.removeprefix("count:")] < position[run.name], run.name
    rows = experiments.comparisons(settings)
    claims = {"count", "budget", "init", "noise", "regularizers", "time", "budget-start", "noise-amount",
              "regularizers-count"}
    claims |= {"init-steps", "init-start"} if settings.ablation_cap else set()
    assert {row.claim for row in rows} == claims
    for row in rows:
        assert row.baseline.name in position and row.variant.name in position, row.label


def _record(name: str, base: str, seed: int, psnr: float, count: int = 1000) -> dict:
    return {"name": name, "base_name": base, "seed": seed, "psnr": psnr, "ssim": 0.9, "lpips": 0.1,
            "num_gaussians": count, "ms_per_step": 10.0, "train_seconds": 20.0}


def test_caps_of_the_same_seed_and_runs_that_cannot_train(tmp_path):
    records = Records(tmp_path)
    records.add(_record("cup-adc-sfm", "cup-adc-sfm", 0, 25.0, count=5000))
    records.add(_record("cup-adc-sfm-seed1", "cup-adc-sfm", 1, 25.1, count=6000))
    adc, mcmc = experiments.same_count_pair("cup", "sfm")
    assert resolve_cap(mcmc, records) == 5000
    assert resolve_cap(mcmc.with_seed(1), records) == 6000
    assert resolve_cap(mcmc.with_seed(2), records) == 5000  # no seed-2 ADC run: the seed-0 count
    with pytest.raises(NotReady, match="has not run"):
        resolve_cap(experiments.same_count_pair("bird", "sfm")[1], records)
    with pytest.raises(NotReady, match="no option mcmc.not_an_option"):
        check_options(experiments.Run("cup", "mcmc", "random", "x", 10, (("mcmc.not_an_option", 1),)))


def test_extra_seeds_where_a_difference_is_small_or_inside_the_baselines_spread(tmp_path):
    scale, records = experiments.SCALES["cpu"], Records(tmp_path)
    reference = experiments.ablation_reference(scale, "cup")
    variants = {name: experiments.Run("cup", "mcmc", "random", name, reference.cap, opts)
                for name, opts in experiments.NOISE_VARIANTS.items()}
    records.add(_record(reference.name, reference.base_name, 0, 25.0))
    records.add(_record(variants["no-noise"].name, variants["no-noise"].base_name, 0, 24.0))     # 1 dB below
    records.add(_record(variants["no-gate"].name, variants["no-gate"].base_name, 0, 24.9))       # 0.1 dB below
    extra = {run.name for run in extra_seed_runs(scale, records)}
    assert "cup-mcmc-random-no-gate-seed1" in extra and f"{reference.name}-seed2" in extra
    assert "cup-mcmc-random-no-noise-seed1" not in extra
    for seed, psnr in ((1, 26.5), (2, 25.2)):  # the reference's own seeds spread 1.5 dB: 1 dB settles nothing
        records.add(_record(reference.with_seed(seed).name, reference.base_name, seed, psnr))
    assert "cup-mcmc-random-no-noise-seed1" in {run.name for run in extra_seed_runs(scale, records)}


def test_churn_counts_the_dead_share_once_the_cap_is_reached(tmp_path):
    (tmp_path / "config.json").write_text('{"mcmc": {"refine_start": 5, "refine_stop": 1000, "refine_every": 10}}')
    lines = [{"step": 100, "num_gaussians": 500, "relocated": 50},     # growing: left out of the share
             {"step": 200, "num_gaussians": 1000, "relocated": 400},    # reached the cap here: left out too
             {"step": 300, "num_gaussians": 1000, "relocated": 2000},   # 10 refine steps x 1000: 20% dead
             {"step": 400, "num_gaussians": 1000, "relocated": 1000}]   # 10%
    (tmp_path / "log.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    figures = churn(tmp_path)
    assert figures["relocated_total"] == 3450 and figures["relocated_per_gaussian"] == pytest.approx(3.45)
    assert figures["dead_per_refine"] == pytest.approx(0.15)


def test_the_page_pairs_seeds_and_keeps_its_prose(tmp_path, monkeypatch):
    scale = experiments.SCALES["cpu"]
    folder = tmp_path / "results"
    monkeypatch.setattr(page.C, "RESULTS", folder)
    records = Records(folder / "paper" / "cpu")
    records.add(_record("lego-adc-random", "lego-adc-random", 0, 30.0))
    records.add(_record("lego-mcmc-random", "lego-mcmc-random", 0, 31.0))
    records.add(_record("lego-mcmc-random-seed1", "lego-mcmc-random", 1, 35.0))  # no ADC seed 1: not paired
    figures = page.Figures(scale)
    row = next(r for r in figures.rows("count") if r.label == "lego, random init")
    assert figures.delta(row) == pytest.approx(1.0) and figures.seed_count(row) == 1

    target = tmp_path / "paper.md"
    target.write_text("# Title\n\nHand-written reading.\n\n<!-- generated: same-count cpu -->\nold\n"
                      "<!-- end: same-count cpu -->\n\nMore prose.\n")
    page.write_page(target)
    text = target.read_text()
    assert "Hand-written reading." in text and "More prose." in text and "\nold\n" not in text
    assert "| lego, random init | 1,000 | 0.0 | 30.00 / 0.900 / 0.100 | 31.00 / 0.900 / 0.100 | +1.00 |" in text
    assert text.count("<!-- generated: same-count cpu -->") == 1
    assert "<!-- generated: noise gpu -->" in text and "Not run yet at gpu scale" in text  # appended blocks
