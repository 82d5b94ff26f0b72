"""`--cap-max auto`: the screen-gradient demand, growth limited by it, the cap fixed once the demand falls, resume."""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import pytest
import torch

from mcsplat.config import TrainConfig, from_jsonable, to_jsonable
from mcsplat.errors import MCSplatError
from mcsplat.metrics import StepValues
from mcsplat.optim import OptimConfig, make_optimizers
from mcsplat.strategy.auto_cap import growth_demand, pixel_ceiling
from mcsplat.strategy.mcmc import MCMCConfig, MCMCReport, MCMCStrategy
from mcsplat.strategy.screen_gradients import ScreenGradients, ndc_gradient_norms

from tests.strategy.test_mcmc import RADIUS, make_model

WIDTH, HEIGHT = 40, 20


def fake_render(grad2d: torch.Tensor, visible: torch.Tensor | None = None) -> SimpleNamespace:
    """What the statistic reads from a render after its backward: means2d.grad (per pixel) and radii."""
    n = grad2d.shape[0]
    radii = torch.ones(n, dtype=torch.int32) if visible is None else visible.to(torch.int32)
    return SimpleNamespace(means2d=SimpleNamespace(grad=grad2d), radii=radii, contributed=radii > 0)


def per_pixel(ndc_norm: float, n: int) -> torch.Tensor:
    """A per-pixel x gradient whose NDC norm (x times width / 2) is `ndc_norm`, for n Gaussians."""
    return torch.tensor([[ndc_norm / (0.5 * WIDTH), 0.0]]).repeat(n, 1)


def test_the_statistic_is_the_mean_ndc_norm_over_the_views_that_saw_each_gaussian():
    g = ScreenGradients()
    grad = torch.tensor([[0.01, 0.0], [0.0, 0.02], [0.03, 0.04]])
    g.add(fake_render(grad), 3, WIDTH, HEIGHT)
    g.add(fake_render(grad * 3, visible=torch.tensor([True, False, False])), 3, WIDTH, HEIGHT)
    expected = torch.tensor([(0.01 * 20 + 0.03 * 20) / 2, 0.02 * 10, ((0.03 * 20) ** 2 + (0.04 * 10) ** 2) ** 0.5])
    torch.testing.assert_close(g.means(), expected)
    assert g.views.tolist() == [2, 1, 1]


def test_the_cpu_loop_adds_what_the_torch_form_adds():
    """float32 on the CPU adds the norms in one loop (screen_gradients.add_norms_cpu): the sums and counts of the
    torch form, over rows that span several of the loop's threads."""
    g = torch.Generator().manual_seed(2)
    n = 5000
    renders = [fake_render(torch.randn(n, 2, generator=g) * 1e-3, torch.rand(n, generator=g) > 0.3) for _ in range(3)]
    stat = ScreenGradients()
    total, views = torch.zeros(n), torch.zeros(n, dtype=torch.int32)
    for render in renders:
        stat.add(render, n, WIDTH, HEIGHT)
        visible, norms = ndc_gradient_norms(render, n, WIDTH, HEIGHT)
        total, views = total + norms, views + visible
    torch.testing.assert_close(stat.total, total, rtol=2e-7, atol=0)
    assert torch.equal(stat.views, views)


def test_demand_counts_live_gaussians_at_or_over_the_threshold():
    g = ScreenGradients()
    g.add(fake_render(torch.cat([per_pixel(3e-4, 4), per_pixel(1e-4, 6)])), 10, WIDTH, HEIGHT)
    opacities = torch.tensor([0.5, 0.5, 0.5, 0.001] + [0.5] * 6)  # one of the four is dead
    assert growth_demand(g, opacities, threshold=2e-4, min_opacity=0.005) == 3
    assert growth_demand(ScreenGradients(), opacities, 2e-4, 0.005) == 0, "no views yet: no demand"


def make_auto(n: int, **options) -> tuple:
    model = make_model([0.5] * n, seed=1)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    config = MCMCConfig(cap_max=10_000, auto_cap=True, refine_start=0, refine_every=10, **options)
    return model, optimizers, MCMCStrategy(config, RADIUS, torch.Generator().manual_seed(0))


def refine(strategy, model, optimizers, step: int, ndc_norms: torch.Tensor) -> MCMCReport:
    """One step whose view gave these NDC gradient norms, then the strategy's refine step."""
    strategy.step_post_backward(step, model, fake_render(ndc_norms[:, None] * torch.tensor([[2.0 / WIDTH, 0.0]])),
                                WIDTH, HEIGHT)
    return strategy.step_post_optimizer(step, model, optimizers, means_lr=0.0)


def test_growth_is_the_demand_capped_at_five_percent_then_the_cap_stays_where_demand_fell():
    model, optimizers, strategy = make_auto(400)
    wanting = torch.zeros(400)
    wanting[:12] = 1e-3  # 12 ask for more (3% of 400): grow by 12, not by 5% (20)
    info = refine(strategy, model, optimizers, 10, wanting)
    assert info.demand == 12 and info.added == 12 and model.num_gaussians == 412
    info = refine(strategy, model, optimizers, 20, torch.full((412,), 1e-3))  # all ask: MCMC's 5%
    assert info.added == int(1.05 * 412) - 412 and strategy.chosen_cap is None
    n = model.num_gaussians
    few = torch.zeros(n)
    few[:3] = 1e-3  # under 1% of N: the count is fixed here
    info = refine(strategy, model, optimizers, 30, few)
    assert info.added == 0 and strategy.chosen_cap == n
    info = refine(strategy, model, optimizers, 40, torch.full((n,), 1e-3))  # demand again: the cap holds
    assert info.added == 0 and info.demand is None and model.num_gaussians == n


def test_the_ceiling_still_holds():
    model, optimizers, strategy = make_auto(400)
    strategy.follow(dataclasses.replace(strategy.schedule, cap_max=405))  # a plan with a lower cap
    info = refine(strategy, model, optimizers, 10, torch.full((400,), 1e-3))
    assert info.added == 5 and model.num_gaussians == 405


def test_a_restored_strategy_takes_the_same_decisions():
    model, optimizers, strategy = make_auto(400)
    refine(strategy, model, optimizers, 10, torch.full((400,), 1e-3))
    # Half an interval of statistics, then a checkpoint.
    strategy.step_post_backward(11, model, fake_render(per_pixel(3e-4, model.num_gaussians)), WIDTH, HEIGHT)
    state = strategy.state_dict()
    twin = MCMCStrategy(MCMCConfig(**state["config"]), RADIUS, torch.Generator())
    twin.load_state_dict(state)
    torch.testing.assert_close(twin.gradients.means(), strategy.gradients.means())
    n = model.num_gaussians
    demand_a = growth_demand(strategy.gradients, model.opacities.detach(), 2e-4, 0.005)
    demand_b = growth_demand(twin.gradients, model.opacities.detach(), 2e-4, 0.005)
    assert demand_a == demand_b == n
    strategy.chosen_cap = 999
    twin.load_state_dict(strategy.state_dict())
    assert twin.chosen_cap == 999


def test_cap_max_auto_in_the_configuration(tmp_path):
    config = TrainConfig(data=tmp_path, cap_max="auto")
    assert config.mcmc.auto_cap and config.mcmc.cap_max == MCMCConfig().cap_max  # the default ceiling
    again = from_jsonable(to_jsonable(config))
    assert again.cap_max == "auto" and again.mcmc.auto_cap
    assert not TrainConfig(data=tmp_path, cap_max=5000).mcmc.auto_cap
    default = TrainConfig(data=tmp_path)  # no --cap-max: the count from the scene, the paper's 1M its ceiling
    assert default.cap_max is None and default.mcmc.auto_cap and default.mcmc.cap_max == 1_000_000
    assert not TrainConfig(data=tmp_path, strategy="adc").adc.cap_max, "ADC's growth has its own rule"
    block = dataclasses.replace(default, cap_max=40_000)  # a block's share of the cap: a number, grown to
    assert not block.mcmc.auto_cap and block.mcmc.cap_max == 40_000
    with pytest.raises(MCSplatError, match="--cap-max auto is for the MCMC strategy"):
        TrainConfig(data=tmp_path, cap_max="auto", strategy="adc")


def test_a_run_without_cap_max_stops_growing_where_the_scene_stops_asking(tmp_path, mini_demo):
    """No --cap-max: a short run of the mini demo grows while its views ask for more Gaussians and stops where they
    stop, below the paper's 1M and the per-pixel ceiling; metrics.json says where. (In 600 steps of a few views
    every Gaussian still asks at 3DGS's threshold; at ten times it the scene stops asking within the run.)"""
    from mcsplat.config import ModelConfig
    from mcsplat.train import train
    metrics = train(TrainConfig(data=mini_demo, out=tmp_path / "run", steps=600, downscale=4, quiet=True,
                                save_every=0, save_renders=False, lpips_net="alex",
                                model=ModelConfig(num_init_points=300), mcmc=MCMCConfig(demand_threshold=0.002)))
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert metrics["auto_cap"] is not None and metrics["auto_cap"] < metrics["auto_cap_ceiling"] < 1_000_000, metrics
    assert metrics["num_gaussians"] == metrics["auto_cap"] > 300, "it grew, then stopped"
    reached = next(r["step"] for r in log if r["num_gaussians"] == metrics["auto_cap"])
    assert all(r["num_gaussians"] == metrics["auto_cap"] for r in log if r["step"] >= reached)


def test_the_log_keeps_the_last_demand_and_sums_the_counts(tmp_path):
    """log.jsonl: relocated/added add up over the refine steps since the last record, the demand is the last one's
    (summed, ten refine steps of 1.5% each would read as 15% of the count)."""
    from mcsplat.run.events import StepDone
    from mcsplat.subscribers import LOG_EVERY, LogWriter

    log = LogWriter(tmp_path / "log.jsonl")
    for step in range(1, LOG_EVERY + 1):
        refine = step % 10 == 0
        report = MCMCReport(num_gaussians=1000, relocated=2 if refine else 0, added=3 if refine else 0,
                            demand=100 + step if refine else None)
        log.on_step_done(StepDone(step=step, total_steps=1000, values=StepValues.of(0.1, 20.0), num_gaussians=1000,
                                  sh_degree=0, train_seconds=1.0, refine=report))
    record = json.loads((tmp_path / "log.jsonl").read_text())
    assert (record["relocated"], record["added"], record["demand"]) == (20, 30, 100 + LOG_EVERY)


def test_the_per_pixel_ceiling_stops_growth_while_the_demand_lasts():
    """3 Gaussians per pixel of a training image: 140 pixels make a ceiling of 420 under cap_max's 10,000."""
    assert pixel_ceiling(10_000, 140, 3.0) == 420
    assert pixel_ceiling(300, 140, 3.0) == 300, "cap_max stays the ceiling where it is lower"
    assert pixel_ceiling(10_000, 140, 0.0) == pixel_ceiling(10_000, None, 3.0) == 10_000, "off, or no images"
    model, optimizers, strategy = make_auto(400)
    strategy.image_pixels = 140
    info = refine(strategy, model, optimizers, 10, torch.full((400,), 1e-3))  # all ask: 5% would be 20
    assert info.added == 20 and model.num_gaussians == 420 and strategy.ceiling == 420
    info = refine(strategy, model, optimizers, 20, torch.full((420,), 1e-3))
    assert info.added == 0 and model.num_gaussians == 420 and strategy.chosen_cap is None
    with pytest.raises(ValueError, match="gaussians_per_pixel"):
        MCMCConfig(gaussians_per_pixel=-1.0)
    assert MCMCStrategy(MCMCConfig(cap_max=500), RADIUS, image_pixels=10).ceiling == 500, "only with auto_cap"
