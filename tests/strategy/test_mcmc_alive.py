"""Relocation "alive" (no copy born dead, no growth while dead are left unplaced) and the health instruments that
show MCMC's collapse at a cap far above what the scene needs."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from mcsplat.gaussians import DEAD_OPACITY, PARAM_KEYS, GaussianModel
from mcsplat.optim import OptimConfig, make_optimizers
from mcsplat.strategy import MCMCConfig, MCMCStrategy
from mcsplat.strategy.health import SeenWindow, refine_health
from mcsplat.strategy.mcmc import eq9_opacities, grow, relocate_dead
from mcsplat.strategy.relocation import (DEFAULT_COPY_FLOOR, copy_capacity, relocation_params, sample_by_weight,
                                         sample_hosts)

RADIUS = 1.0


def make_model(opacities, seed: int = 0) -> GaussianModel:
    opacities = torch.as_tensor(opacities, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    model = GaussianModel.empty(opacities.shape[0])
    with torch.no_grad():
        for key in PARAM_KEYS:
            model.params[key].copy_(torch.randn(model.params[key].shape, generator=g))
        model.params["opacity_logits"].copy_(torch.logit(opacities).float())
    return model


def crowded(live: int = 20, dead: int = 400, opacity: float = 0.2) -> GaussianModel:
    """A few faint live Gaussians and many dead ones: a model at a cap far above what its scene holds."""
    return make_model([opacity] * live + [0.001] * dead, seed=3)


# ----------------------------------------------------------------------------------------------- the capacity
@pytest.mark.parametrize("opacity", [0.021, 0.05, 0.2, 0.5, 0.9, 0.999])
@pytest.mark.parametrize("floor", [0.01, DEFAULT_COPY_FLOOR, 0.1])
def test_capacity_is_the_most_copies_whose_eq9_opacity_stays_at_the_floor(opacity, floor):
    copies = int(copy_capacity(torch.tensor([opacity]), floor, n_max=1000)[0])
    at = lambda n: 1.0 - (1.0 - opacity) ** (1.0 / n)  # noqa: E731  (Eq. 9's opacity with n sharing)
    if opacity < floor:
        assert copies == 0
        return
    assert at(copies + 1) >= floor * (1 - 1e-9)
    assert at(copies + 2) < floor


def test_capacity_stays_within_eq9s_clamp_and_gives_nothing_below_the_floor():
    capacity = copy_capacity(torch.tensor([0.999999, 0.5, 0.019, 0.004]), DEFAULT_COPY_FLOOR, n_max=51)
    assert capacity.tolist()[0] == 50 and capacity.tolist()[2:] == [0, 0]


def test_sample_hosts_never_exceeds_a_capacity_and_fills_what_fits():
    weights = torch.tensor([1.0, 5.0, 0.0, 2.0])
    capacity = torch.tensor([3, 2, 9, 40])
    drawn = sample_hosts(weights, capacity, 20, torch.Generator().manual_seed(0))
    counts = torch.bincount(drawn, minlength=4)
    assert drawn.numel() == 20 and (counts <= capacity).all() and counts[2] == 0
    # More asked than the hosts can take: every host full, the rest not drawn.
    drawn = sample_hosts(weights, capacity, 100, torch.Generator().manual_seed(0))
    assert torch.bincount(drawn, minlength=4).tolist() == [3, 2, 0, 40]


def test_sample_hosts_with_room_to_spare_draws_like_sample_by_weight():
    weights = torch.tensor([0.2, 0.3, 0.5])
    drawn = sample_hosts(weights, torch.full((3,), 10**6), 20_000, torch.Generator().manual_seed(1))
    shares = torch.bincount(drawn, minlength=3).double() / 20_000
    assert torch.allclose(shares, weights.double(), atol=0.015)
    assert torch.equal(drawn, sample_by_weight(weights, 20_000, torch.Generator().manual_seed(1)))  # the same draws


# ---------------------------------------------------------------------------------------- relocation, growth
def test_the_papers_relocation_gives_copies_born_dead_on_a_crowded_model():
    """The mechanism: 20 hosts of 0.05 share 400 dead slots, about 21 copies to a host, at 1 - 0.95^(1/21) = 0.0024
    each: under the dead threshold, where the clamp leaves them, dead when born."""
    model = crowded(opacity=0.05)
    before = model.opacities.detach().clone()
    slots, sources = relocate_dead(model, make_optimizers(model, OptimConfig(), RADIUS),
                                   torch.Generator().manual_seed(0))
    assert slots.numel() == 400
    born = eq9_opacities(before, sources, 51, DEAD_OPACITY)
    assert float((born <= DEAD_OPACITY).double().mean()) > 0.8
    assert float((model.opacities.detach()[slots] <= DEAD_OPACITY * 1.0001).double().mean()) > 0.8


@pytest.mark.parametrize("opacity", [0.08, 0.2, 0.6])
def test_alive_relocation_gives_no_copy_born_dead_and_leaves_the_rest_unplaced(opacity):
    model = crowded(opacity=opacity)
    before = model.opacities.detach().clone()
    slots, sources = relocate_dead(model, make_optimizers(model, OptimConfig(), RADIUS),
                                   torch.Generator().manual_seed(0), copy_floor=DEFAULT_COPY_FLOOR)
    capacity = int(copy_capacity(torch.tensor([opacity]), DEFAULT_COPY_FLOOR)[0])
    assert slots.numel() == min(400, 20 * capacity)
    after = model.opacities.detach()
    touched = torch.cat([slots, torch.unique(sources)])
    assert float(after[touched].min()) >= DEFAULT_COPY_FLOOR * (1 - 1e-5)
    # Each host and its copies still look like the host did (Eq. 9's centre value).
    for host in torch.unique(sources).tolist():
        n = int((sources == host).sum()) + 1
        assert (1 - float(after[host])) ** n == pytest.approx(1 - float(before[host]), abs=1e-5)
    unplaced = torch.ones(420, dtype=torch.bool)
    unplaced[:20] = False
    unplaced[slots] = False
    assert (after[unplaced] <= DEAD_OPACITY).all()  # left where they were, still dead


def test_alive_growth_gives_no_copy_born_dead():
    model = make_model([0.03] * 100 + [0.9] * 5, seed=4)
    sources = grow(model, make_optimizers(model, OptimConfig(), RADIUS), torch.Generator().manual_seed(2),
                   cap_max=10_000, grow_rate=3.0, copy_floor=DEFAULT_COPY_FLOOR)
    assert 0 < sources.numel() <= 210
    assert float(model.opacities.detach().min()) >= DEFAULT_COPY_FLOOR * (1 - 1e-5)
    # The faint hosts (capacity 0 at 0.03: one copy would give 0.015) gave nothing.
    assert (sources >= 100).all()


def test_the_strategy_does_not_grow_while_dead_are_left_unplaced():
    model = crowded(opacity=0.08)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=10_000), RADIUS, torch.Generator().manual_seed(0))
    report = strategy.step_post_optimizer(600, model, optimizers, means_lr=0.0)
    assert report.added == 0 and report.num_gaussians == 420
    assert report.unplaced == 400 - report.relocated > 0 and report.born_dead_share == 0.0
    paper = MCMCStrategy(MCMCConfig(cap_max=10_000, relocation="paper"), RADIUS, torch.Generator().manual_seed(0))
    model = crowded(opacity=0.08)
    report = paper.step_post_optimizer(600, model, make_optimizers(model, OptimConfig(), RADIUS), means_lr=0.0)
    assert report.relocated == 400 and report.added == 21 and report.born_dead_share > 0.5


def test_where_hosts_have_room_alive_relocation_is_the_papers():
    """A healthy model (few dead, opaque hosts): the same draws, the same parameters, bit for bit."""
    opacities = [0.7] * 200 + [0.001] * 10
    rows = []
    for relocation in ("alive", "paper"):
        model = make_model(opacities, seed=5)
        strategy = MCMCStrategy(MCMCConfig(cap_max=300, relocation=relocation), RADIUS,
                                torch.Generator().manual_seed(9))
        report = strategy.step_post_optimizer(600, model, make_optimizers(model, OptimConfig(), RADIUS), means_lr=0.0)
        assert report.relocated == 10 and report.added == 10 and report.unplaced == 0
        flat = torch.cat([model.params[key].detach().reshape(model.num_gaussians, -1) for key in PARAM_KEYS], 1)
        rows.append(flat)
    assert torch.equal(rows[0], rows[1])


# ----------------------------------------------------------------------------------------------- instruments
def test_seen_window_and_the_unseen_share_of_the_dead():
    window = SeenWindow()
    window.add(SimpleNamespace(contributed=torch.tensor([True, False, False, False])), 4)
    window.add(SimpleNamespace(contributed=torch.tensor([False, False, True, False])), 4)
    dead = torch.tensor([True, True, True, False])
    assert window.unseen_share(dead) == pytest.approx(1 / 3)
    window.reset()
    assert window.unseen_share(dead) is None
    with pytest.raises(ValueError, match="the render has 3 Gaussians but the model 4"):
        window.add(SimpleNamespace(contributed=torch.zeros(3, dtype=torch.bool)), 4)


def test_refine_health_levels():
    sources = torch.tensor([0, 0, 0, 2, 5])
    born = torch.tensor([0.004, 0.005, 0.02, 0.3, 0.5], dtype=torch.float64)
    levels = refine_health(100, 25, 0.4, sources, born, DEAD_OPACITY, unplaced=3)
    assert levels == {"dead_share": 0.25, "unplaced": 3.0, "unseen_dead_share": 0.4, "copies_max": 3.0,
                      "copies_mean": pytest.approx(5 / 3, abs=1e-3), "born_dead_share": 0.4}


def test_eq9_opacities_match_relocation_params():
    opacities = torch.tensor([0.3, 0.9, 0.01, 0.5])
    sources = torch.tensor([1, 1, 1, 0, 3, 1])
    counts = torch.bincount(sources, minlength=4)[sources] + 1
    expected, _ = relocation_params(opacities[sources], torch.ones(6, 3), counts)
    assert torch.allclose(eq9_opacities(opacities, sources, 51, DEAD_OPACITY).float(), expected, atol=1e-7)
    assert math.isclose(float(eq9_opacities(opacities, sources, 51, DEAD_OPACITY)[0]), 1 - 0.1 ** 0.2, rel_tol=1e-6)


def _view(num: int, asking: int) -> SimpleNamespace:
    """A render after its backward in which the first `asking` of `num` Gaussians have a screen gradient far above
    3DGS's threshold and the rest none; all of them composited."""
    grad = torch.zeros(num, 2)
    grad[:asking, 0] = 1.0
    return SimpleNamespace(means2d=SimpleNamespace(grad=grad), radii=torch.ones(num, dtype=torch.int32),
                           contributed=torch.ones(num, dtype=torch.bool))


@pytest.mark.parametrize("relocation, grows", [("alive", False), ("paper", True)])
def test_with_a_cap_far_above_the_scene_growth_stops_where_it_stops_asking(relocation, grows):
    """--cap-max 10,000 on a model of 400 whose views ask for more in 2 of them (under 1%): relocation alive keeps
    the count there for the rest of the run; the paper's grows on to the cap. While 10% ask, both grow at the
    paper's 5%."""
    model = make_model([0.6] * 400, seed=7)
    optimizers = make_optimizers(model, OptimConfig(), RADIUS)
    strategy = MCMCStrategy(MCMCConfig(cap_max=10_000, relocation=relocation), RADIUS,
                            torch.Generator().manual_seed(0))
    assert strategy.asks_the_scene == (relocation == "alive")
    strategy.step_post_backward(599, model, _view(400, 40), 100, 100)
    report = strategy.step_post_optimizer(600, model, optimizers, means_lr=0.0)
    assert report.added == 20 and model.num_gaussians == 420
    for step in (700, 800):
        strategy.step_post_backward(step - 1, model, _view(model.num_gaussians, 2), 100, 100)
        strategy.step_post_optimizer(step, model, optimizers, means_lr=0.0)
    assert (model.num_gaussians > 420) == grows
    assert (strategy.chosen_cap == 420) == (not grows)
