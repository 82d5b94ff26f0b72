"""Training to the time and the length the user has: the schedules follow --steps, --budget stops on time, coarse to
fine reaches full size, growth reaches the cap, and a scene without points starts from points triangulated from its
known poses."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.data import load_scene
from mcsplat.data.undistort import CACHE_ENV
from mcsplat.errors import MCSplatError
from mcsplat.initialization import initial_model
from mcsplat.initialization.frustum import points_in_frustums
from mcsplat.io.transforms import write_transforms
from mcsplat.planning import Plan, initial_plan
from mcsplat.planning.budget import END_SLACK, BudgetPlanner, StepCost
from mcsplat.planning.schedule import planned_growth_rate, refine_steps_between
from mcsplat.train import train

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


# ------------------------------------------------------------------------------------------------- the schedules
def test_the_step_schedules_follow_the_steps():
    """--steps 3000 gets the paper's schedule at a tenth: refinement 50..2,500 every 10, SH every 100, ADC's
    densification 50..1,500 every 10 and resets every 300; --no-scale-schedule keeps the options as they are."""
    fitted = initial_plan(TrainConfig(data=DEMO, steps=3000))
    m, a = fitted.schedule, initial_plan(TrainConfig(data=DEMO, steps=3000, strategy="adc")).schedule
    assert (fitted.strategy, type(a).__name__) == ("mcmc", "ADCSchedule"), "a plan holds its run's strategy's schedule"
    assert (m.refine_start, m.refine_stop, m.refine_every, fitted.sh_increase_every) == (50, 2500, 10, 100)
    assert (a.densify_start, a.densify_stop, a.densify_every, a.reset_every) == (50, 1500, 10, 300)
    assert Plan.literal(TrainConfig(data=DEMO, steps=3000)).schedule.refine_start == 500, \
        "a resumed run is not fitted twice (its saved values are the plan's, taken as they are)"
    paper = initial_plan(TrainConfig(data=DEMO))
    assert (paper.schedule.refine_start, paper.schedule.refine_stop, paper.schedule.refine_every) == (500, 25_000, 100)
    literal = initial_plan(TrainConfig(data=DEMO, steps=3000, scale_schedule=False))
    assert (literal.schedule.refine_start, literal.schedule.refine_every, literal.sh_increase_every) == (500, 100, 1000)


def test_the_resolution_rises_from_the_start_size_to_full_size():
    plan = initial_plan(TrainConfig(data=DEMO, steps=1000, resolution_start=0.25, resolution_full_at=0.4))
    scales = [plan.resolution_at(step) for step in range(1000)]
    assert scales[0] == pytest.approx(0.25) and scales[200] == pytest.approx(0.5)
    assert all(b >= a for a, b in zip(scales, scales[1:])) and scales[400:] == [1.0] * 600
    assert {initial_plan(TrainConfig(data=DEMO, steps=1000)).resolution_at(step) for step in range(1000)} == {1.0}
    assert TrainConfig(data=DEMO, budget="2m").resolution_start == 0.25, "--budget trains coarse to fine"


def test_growth_is_planned_to_reach_the_cap_in_time():
    """From 100 to 50,000 Gaussians is 128 refine steps at the paper's 5%: more than a 3,000-step run has before
    40% of it (114); the planned rate gets there, and the paper's 5% stays where it is fast enough."""
    plan = initial_plan(TrainConfig(data=DEMO, steps=3000))
    rate = planned_growth_rate(plan, 0.4, 100, 50_000)
    refines = refine_steps_between(plan.schedule.refine_start, round(0.4 * 3000), plan.schedule.refine_every)
    assert refines == 114 and rate > 1.05
    count = 100
    for _ in range(refines):
        count = min(50_000, int(rate * count))  # as MCMC grows: int(rate N), at most the cap
    assert count == 50_000
    assert planned_growth_rate(initial_plan(TrainConfig(data=DEMO)), 0.4, 100_000, 1_000_000) == 1.05


def test_a_short_run_grows_to_its_cap(tmp_path, mini_demo):
    """A 600-step run (schedules / 50: refinement every 2 steps from step 10) from 300 points reaches its cap of
    3,000 by 40% of the run; with the paper's schedule taken literally it would refine once and not get there."""
    metrics = train(TrainConfig(data=mini_demo, out=tmp_path / "run", steps=600, downscale=4, cap_max=3000,
                                quiet=True, save_every=0, save_renders=False, lpips_net="alex",
                                model=ModelConfig(num_init_points=300)))
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    reached = next(record["step"] for record in log if record["num_gaussians"] == 3000)
    assert metrics["num_gaussians"] == 3000 and reached <= 0.4 * 600, log


# ---------------------------------------------------------------------------------------------------- --budget
def test_the_budget_planner_fills_the_time_with_the_balanced_cap():
    """With a known step cost (10 ms + 40 ms s^2 + 20 ms per 100k Gaussians at full size), a 120 s budget plans the
    cap where Gaussians cost twice as much as pixels (2 x (a + b) = 100 ms = 500k Gaussians) x sqrt(120 / 600), and
    steps whose predicted times add up to the budget."""
    config = TrainConfig(data=DEMO, budget="120s", model=ModelConfig(num_init_points=1000))
    planner = BudgetPlanner(config, ceiling=1_000_000)
    for n, s in ((1000, 1.0), (1000, 0.25), (300_000, 1.0), (300_000, 0.25), (50_000, 0.5)):
        planner.calibrate(0.010 + 0.040 * s * s + 0.2e-6 * n, n, s)
    planner.start(0, 0.0, 1000)
    plan = planner.plan
    assert plan.schedule.cap_max == pytest.approx(500_000 * math.sqrt(0.2), rel=0.01)
    ks = np.arange(plan.steps)
    scales = np.array([plan.resolution_at(int(k)) for k in ks])
    assert scales[0] == pytest.approx(0.25) and scales[-1] == 1.0
    upper = np.sum(0.010 + 0.040 * scales ** 2 + 0.2e-6 * plan.schedule.cap_max)  # every step at the cap
    lower = np.sum(0.010 + 0.040 * scales ** 2 + 0.2e-6 * 1000)                 # every step at the start count
    assert lower < 120.0 < upper and 1000 < plan.steps
    assert plan.schedule.refine_every == max(1, round(100 * plan.steps / 30_000))
    assert plan.budget["history"][0]["steps"] == plan.steps
    assert config.steps == 30_000 and config.mcmc.cap_max == 1_000_000, "the plan is its own: the options stay"


def _known_costs(budget: str = "120s", pixels: float = 0.040, per_gaussian: float = 0.2e-6) -> BudgetPlanner:
    """A planner calibrated on steps of 10 ms + `pixels` s^2 + `per_gaussian` n, started at 1,000 Gaussians."""
    config = TrainConfig(data=DEMO, budget=budget, model=ModelConfig(num_init_points=1000))
    planner = BudgetPlanner(config, ceiling=1_000_000)
    probes = ((1000, 1.0), (1000, 0.25), (300_000, 1.0), (300_000, 0.25), (50_000, 0.5))
    for n, s in probes:
        planner.calibrate(0.010 + pixels * s * s + per_gaussian * n, n, s)
    planner.start(0, 0.0, 1000)
    return planner


def test_a_run_ahead_of_its_plan_plans_again_to_end_on_time():
    """Steps that ran faster than measured bring the run to its planned step early: with most of the budget left
    it plans more steps; within END_SLACK of the budget it ends there."""
    config = TrainConfig(data=DEMO, budget="120s", model=ModelConfig(num_init_points=1000))
    planner = BudgetPlanner(config, ceiling=100_000)
    for n, s in ((1000, 1.0), (1000, 0.25), (100_000, 1.0), (100_000, 0.25)):
        planner.calibrate(0.010 + 0.040 * s * s + 0.2e-6 * n, n, s)
    planner.start(0, 0.0, 1000)
    planner.replan(100, 10.0, 1000)
    reached = planner.plan.steps
    assert not planner.due(reached - 1, 10.5), "planned half a second ago: not due yet"
    assert planner.due(reached, 10.5) and planner.finished(reached, 10.5), "at the planned step, 90% of the time left"
    planner.replan(reached, 10.5, planner.plan.schedule.cap_max)
    assert planner.plan.steps > reached and not planner.finished(reached, 10.5)
    assert not planner.due(planner.plan.steps, (1 - END_SLACK / 2) * 120.0), "the time is nearly up: the run ends"


def _planned(pixels_ms: float, per_100k_ms: float, cap: int = 100_000, **options) -> BudgetPlanner:
    """A 120 s budget planned from known costs: 5 ms + pixels_ms s^2 + per_100k_ms per 100k Gaussians at s^2."""
    config = TrainConfig(data=DEMO, budget="120s", model=ModelConfig(num_init_points=1000), **options)
    planner = BudgetPlanner(config, ceiling=cap)
    for n, s in ((1000, 1.0), (1000, 0.25), (cap, 1.0), (cap, 0.25)):
        planner.calibrate(0.005 + (pixels_ms + per_100k_ms * n / 1e5) * s * s / 1000, n, s)
    planner.start(0, 0.0, 1000)
    return planner


def test_the_coarse_phase_lasts_longer_where_pixels_take_more_of_a_step():
    """Full size comes at 40% of the run where a full-size step is mostly overhead (pixels a sixth of it), at the
    end where its pixels take 90% of it, at 55% where they take half; --resolution-full-at is kept as given; once
    full size is reached the length is kept, and a resumed run goes on choosing it."""
    cheap = _planned(pixels_ms=5, per_100k_ms=0)  # 10 ms a full-size step, half of it pixels
    assert cheap.pixel_share(100_000) == pytest.approx(5 / 10, rel=0.02)
    assert cheap.plan.resolution_full_at == pytest.approx(0.55, abs=0.02)
    assert _planned(pixels_ms=1, per_100k_ms=0).plan.resolution_full_at == pytest.approx(0.4)  # pixels 1/6
    dear = _planned(pixels_ms=45, per_100k_ms=0)  # pixels 90% of a step
    assert dear.plan.resolution_full_at == pytest.approx(1.0)
    scales = [dear.plan.resolution_at(k) for k in range(dear.plan.steps)]
    assert scales[0] == pytest.approx(0.25) and scales[-2] < 1.0 and dear.plan.steps > 1000
    assert _planned(pixels_ms=45, per_100k_ms=0, resolution_full_at=0.5).plan.resolution_full_at == 0.5

    # Past full size the length stays, whatever the costs say from then on.
    cheap.replan(round(0.6 * cheap.plan.steps), 60.0, 1000)
    kept = cheap.plan.resolution_full_at
    for _ in range(20):
        cheap.observe(0.050, 1000, 1.0)  # pixels now look dear
    cheap.replan(round(0.6 * cheap.plan.steps), 61.0, 1000)
    assert cheap.plan.resolution_full_at == kept

    # A resumed run reads the choice back from its plan's record (config.json holds the number in the option's place).
    resumed = BudgetPlanner(TrainConfig(data=DEMO, budget="120s", resolution_full_at=dear.plan.resolution_full_at),
                            ceiling=100_000, plan=dear.plan)
    assert resumed.full_size_chosen and dear.plan.budget["full_size_chosen"]


def test_a_new_plan_goes_on_from_the_size_the_run_trains_at():
    """Costs that swing make the coarse phase's length move back and forth from plan to plan; each new plan's curve
    passes through the size of the step it is made at, so the size the run trains at never falls back, nor jumps
    up before full size is due."""
    planner = _planned(pixels_ms=20, per_100k_ms=0)
    step, lengths, sizes = 0, [], []
    for i in range(10):
        step += planner.plan.steps // 30
        before = planner.plan.resolution_at(step)
        for _ in range(30):  # pixels alternately dear and cheap: the chosen length swings
            size = planner.plan.resolution_at(step)
            planner.observe(0.005 + (0.060 if i % 2 == 0 else 0.001) * size * size, 1000, size)
        planner.replan(step, 1.0 + i, 1000)
        lengths.append(planner.plan.resolution_full_at)
        sizes.append(planner.plan.resolution_at(step))
        assert sizes[-1] == pytest.approx(before) or sizes[-1] == 1.0, f"plan {i}: {before:.3f} -> {sizes[-1]:.3f}"
        assert planner.plan.resolution_at(step + 1) >= sizes[-1]
    moves = np.diff(lengths)
    assert moves.max() > 0.03 and moves.min() < -0.03, f"the length should swing both ways: {lengths}"
    assert all(b >= a for a, b in zip(sizes, sizes[1:])), sizes


def test_the_step_cost_model_recovers_known_costs():
    """Calibrated at two sizes and two counts, then measured along a run that grows and sharpens as runs do."""
    def seconds(n, s):
        return 0.005 + 0.08 * s * s + 0.1e-6 * n + 0.3e-6 * n * s * s

    cost = StepCost()
    for n, s in ((2000, 1.0), (2000, 0.25), (100_000, 1.0), (300_000, 1.0), (300_000, 0.25)):
        cost.add(seconds(n, s), n, s, calibration=True)
    for step in range(600):
        n, s = int(min(300_000, 10_000 * 1.01 ** step)), min(1.0, 0.25 ** (1 - step / 300))
        cost.add(seconds(n, s), n, s)
    cost.fit()
    np.testing.assert_allclose(cost.coefficients, [0.005, 0.08, 0.01, 0.03], rtol=0.05, atol=1e-4)


def test_a_budget_run_stops_on_time_and_records_its_plan(tmp_path, mini_demo):
    metrics = train(TrainConfig(data=mini_demo, out=tmp_path / "run", budget="8s", downscale=2, quiet=True,
                                save_every=0, save_renders=False, lpips_net="alex"))
    assert metrics["budget_seconds"] == 8.0 and abs(metrics["wall_seconds"] - 8.0) <= 0.05 * 8.0, metrics
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    plan = config["plan"]["budget"]
    assert config["plan"]["steps"] == metrics["steps"] and len(plan["history"]) >= 5
    assert config["budget"] == "8s" and config["steps"] == TrainConfig(data=DEMO).steps, "the options as asked"
    assert plan["history"][-1]["at_seconds"] > 0.8 * 8.0, "planned again until near the end"
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["resolution"] == 1.0, "full size at the end"
    sizes = [record["resolution"] for record in log if "resolution" in record]
    assert all(b >= a for a, b in zip(sizes, sizes[1:])), f"the size never steps back: {sizes}"
    report = (tmp_path / "run" / "report.html").read_text()
    assert "planned as it ran" in report and "from 0.25 of the image size" in report, "the report shows the plan"
    assert plan["resolution_first"] == 0.25


def test_budget_errors_are_one_line(tmp_path):
    for budget in ("soon", "-5m", "0"):
        with pytest.raises(MCSplatError, match="--budget .* is not a duration"):
            TrainConfig(data=DEMO, budget=budget)


def test_a_budget_with_steps_is_refused_before_anything_is_made(tmp_path, mini_demo, capsys):
    """--budget plans the steps: a --steps beside it would be ignored, so the pair is refused."""
    from mcsplat.cli import main

    run = tmp_path / "runs" / "run"
    assert main(["train", str(mini_demo), "--out", str(run), "--budget", "5s", "--steps", "60", "--quiet"]) == 2
    assert capsys.readouterr().err == "mcsplat: error: --budget 5s plans the steps itself, so --steps 60 would be " \
        "ignored; give one of them\n"
    assert not (tmp_path / "runs").exists()


# ------------------------------------------------------------------------------------------- initial points
def test_background_follows_the_images_alpha(shared_data):
    assert load_scene(shared_data / "ngp_fruit").background == (0.0, 0.0, 0.0), "a real capture in transforms.json"
    lego = load_scene(DEMO)
    assert lego.alpha and lego.object_centric and lego.background == (1.0, 1.0, 1.0)


def test_points_in_the_frustums_are_in_front_of_the_cameras_and_coloured_by_them():
    scene = load_scene(DEMO)
    points, colors = points_in_frustums(scene.train[:5], scene.radius, 2000, torch.Generator().manual_seed(0))
    seen = torch.zeros(2000, dtype=torch.bool)
    for view in scene.train[:5]:
        camera = view.camera
        in_camera = points @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
        px = in_camera[:, :2] / in_camera[:, 2:] * torch.tensor([camera.fx, camera.fy]) + \
            torch.tensor([camera.cx, camera.cy])
        seen |= (in_camera[:, 2] > 0) & (px >= 0).all(1) & (px[:, 0] < camera.width) & (px[:, 1] < camera.height)
    assert seen.all() and colors.min() >= 0 and colors.max() <= 1 and colors.std() > 0.05


CUP_VIEWS = ["1.jpg", "4.jpg", "7.jpg", "10.jpg", "13.jpg", "16.jpg", "19.jpg", "22.jpg", "25.jpg", "28.jpg"]


def test_a_scene_without_points_starts_from_points_triangulated_from_its_poses(shared_data, tmp_path, monkeypatch):
    """The cup's photos and poses as a transforms.json without points: the triangulated points lie on the cup's
    own SfM points (COLMAP triangulated them from the same photos), and a second run reads them from the cache."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    cup = load_scene(shared_data / "colmap_cup", test_every=0)
    chosen = [view for view in cup.train if f"{view.name}.jpg" in CUP_VIEWS]
    write_transforms(chosen, tmp_path / "scene" / "transforms.json")
    scene = load_scene(tmp_path / "scene", test_every=0)
    assert scene.points is None and not scene.alpha
    config = TrainConfig(data=scene.root, threads=2)
    model, note = initial_model(config, scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    assert "triangulated from the known poses of 10 views" in note and model.num_gaussians > 500, note
    distance, _ = cKDTree(cup.points.numpy()).query(model.means.detach().numpy())
    assert np.median(distance) < 0.01 * cup.radius, np.median(distance) / cup.radius
    again, note = initial_model(config, scene, torch.device("cpu"), torch.Generator().manual_seed(0))
    assert "from the cache" in note and torch.equal(again.means, model.means)


def test_a_resumed_budget_run_keeps_the_ceiling_it_started_with():
    """config.json holds what was asked (--mcmc.cap-max's 1M) and the plan's cap beside it; read back, the run's
    ceiling is the one it started with. A file of the older layout held the last plan's cap in --mcmc.cap-max's
    place: the plan's record keeps the ceiling for it (before, a run stopped at a planned cap of 3,148 resumed capped
    there)."""
    from types import SimpleNamespace
    from mcsplat.planning import options_with_plan, read_record, run_record
    from mcsplat.planning.budget import budget_planner
    config = TrainConfig(data=DEMO, budget="120s", model=ModelConfig(num_init_points=1000))
    scene = SimpleNamespace(train_image_pixels=200 * 200)
    planner = budget_planner(config, Plan.literal(config), scene)
    assert planner.ceiling == 120_000  # 3 per pixel of a 200x200 image, under the 1M of --mcmc.cap-max
    for n, s in ((1000, 1.0), (1000, 0.25), (100_000, 1.0), (100_000, 0.25)):
        planner.calibrate(0.010 + 0.010 * s * s + 0.5e-6 * n, n, s)
    planner.start(0, 0.0, 1000)
    assert planner.plan.schedule.cap_max < planner.ceiling
    saved, plan = read_record(json.loads(json.dumps(run_record(config, planner.plan))))
    assert saved.mcmc.cap_max == 1_000_000 and plan.schedule.cap_max == planner.plan.schedule.cap_max
    assert budget_planner(saved, plan, scene).ceiling == 120_000
    older = json.loads(json.dumps(options_with_plan(config, planner.plan)))
    saved, plan = read_record(older)
    assert saved.mcmc.cap_max == planner.plan.schedule.cap_max, \
        "the older layout: the option's place held the plan's cap"
    assert budget_planner(saved, plan, scene).ceiling == 120_000


def test_a_budget_run_stopped_and_resumed_keeps_its_ceiling(tmp_path, mini_demo, monkeypatch):
    """Issue 58 #3, end to end: a --budget run without --cap-max stopped by a signal, then resumed. config.json
    holds the plan's cap at the stop beside the options; the resumed run's ceiling is still the one it started
    with, where it used to be that planned cap (a 40 s lego run stopped and resumed ended at 3,148
    Gaussians and 21.5 dB; uninterrupted, 9,044 and 25.0 dB)."""
    import signal

    from tests.run.test_run_folder import before_each_step

    def stop(step: int) -> None:
        if step == 12:
            signal.raise_signal(signal.SIGTERM)

    config = TrainConfig(data=mini_demo, out=tmp_path / "run", budget="4s", downscale=2, quiet=True,
                         save_renders=False, lpips_net="alex")
    with monkeypatch.context() as patch:
        before_each_step(patch, stop)
        with pytest.raises(MCSplatError, match="stopped at step 13.*--resume"):
            train(config)
    stopped = json.loads((tmp_path / "run" / "config.json").read_text())
    ceiling = stopped["plan"]["budget"]["ceiling"]
    assert stopped["cap_max"] is None and stopped["mcmc"]["cap_max"] == 1_000_000, "what was asked"
    assert stopped["plan"]["mcmc"]["cap_max"] == stopped["plan"]["budget"]["cap"] <= ceiling
    metrics = train(replace(config, resume=True))
    resumed = json.loads((tmp_path / "run" / "config.json").read_text())
    assert resumed["plan"]["budget"]["ceiling"] == ceiling, "the ceiling the run started with, not its planned cap"
    assert metrics["steps"] > 13 and metrics["num_gaussians"] <= ceiling


def test_the_planners_curves_give_numpy_no_warning_at_their_extremes():
    """A start size that underflowed to 0 and growth at a huge rate made numpy warn ("divide by zero encountered in
    power", "overflow encountered in power") on real captures' consoles; the curves now stay in range."""
    import warnings
    planner = _known_costs(pixels=0.010)
    planner.plan = replace(planner.plan, resolution_start=0.0, resolution_full_at=0.5)
    planner.scale_now = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seconds = planner._future_seconds(0, 5000, 1, 10**9)
        trial = planner._fitted(5000)
        counts = planner._counts(trial, 0, np.arange(0, 5000, 7.0), 1, 10**9)
    assert math.isfinite(seconds) and np.isfinite(counts).all() and counts.max() <= 10**9


def test_once_the_scene_stops_asking_the_plan_gives_the_time_to_steps():
    """The automatic cap fixed its count at 20,000 (the scene asks for no more): the next plan keeps that count
    and fills the time with steps, where it would otherwise still plan growth to the affordable cap."""
    from types import SimpleNamespace
    growing = _known_costs(budget="10m", pixels=0.010)
    growing.strategy = SimpleNamespace(chosen_cap=None)
    growing.replan(500, 30.0, 20_000)
    stopped = _known_costs(budget="10m", pixels=0.010)
    stopped.strategy = SimpleNamespace(chosen_cap=20_000)
    stopped.replan(500, 30.0, 20_000)
    assert growing.plan.schedule.cap_max > 20_000 and stopped.plan.schedule.cap_max == 20_000
    assert stopped.plan.steps > growing.plan.steps
