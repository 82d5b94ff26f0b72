"""benchmarks/paper (the paper's claims as runs): every comparison has its runs, every run that takes another's count
comes after it, the seeds of a comparison are paired, and the page keeps its prose when its tables are rewritten."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # `benchmarks` as a package, as `python -m benchmarks.paper` imports it

from benchmarks.paper import experiments, page  # noqa: E402
from benchmarks.paper.runner import NotReady, Records, check_options, resolve_cap  # noqa: E402


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
    claims = {"count", "budget", "init", "noise", "regularizers", "time"}
    claims |= {"budget-start"} | ({"init-steps"} if settings.ablation_cap else set())
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
