"""benchmarks/sparse_depth.py's page: each arm's change is paired with the same seed's run without sparse depth."""

from __future__ import annotations

import pytest

import sparse_depth


def record(scene, arm, seed, psnr, depth_error=0.01):
    return {"scene": scene, "arm": arm, "seed": seed, "steps": 2000, "psnr": psnr, "depth_error": depth_error,
            "num_gaussians": 30_000, "train_seconds": 40.0}


def test_changes_are_paired_by_seed_and_steps():
    records = [record("cup", "off", 0, 28.0, 0.09), record("cup", "off", 1, 30.0, 0.11),
               record("cup", "half-way", 0, 27.9), record("cup", "half-way", 1, 29.7),
               record("cup", "fade-out", 1, 30.2)]
    page = sparse_depth.report(records, None)
    # Seeds 2 dB apart; the changes against the same seed: -0.1 and -0.3, mean -0.2, standard error 0.1.
    assert "| cup | 2,000 | half-way | 2 | 28.80 | -0.20 dB (0.10, 2 seeds) | 1.0% |" in page
    assert "| cup | 2,000 | off | 2 | 29.00 | - | 10.0% |" in page
    assert "| cup | 2,000 | fade-out | 1 | 30.20 | +0.20 dB (nan, 1 seeds) |" in page
    assert "| cup | half-way | 1 | 29.70 | -0.30 |" in page  # the run's own row
    longer = sparse_depth.report([*records, {**record("cup", "half-way", 0, 40.0), "steps": 4000}], None)
    assert "| cup | 2,000 | half-way | 2 | 28.80 | -0.20 dB (0.10, 2 seeds) |" in longer  # not averaged with it
    assert "| cup | 4,000 | half-way | 1 | 40.00 | - |" in longer  # no run without sparse depth at 4,000 steps


@pytest.mark.parametrize("arm", sparse_depth.ARMS)
def test_every_arm_names_a_schedule_of_the_term(arm):
    options = sparse_depth.ARMS[arm]
    assert (arm == "off") == (options.get("sparse_depth", 0) == 0)
