"""--depth-correlation, the worked example of docs/extending.md ("A feature"): the loss, its options as a group of
TrainConfig, and the feature seam that hands the run its term."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mcsplat.cli import COMMANDS
from mcsplat.config import config_of, to_jsonable
from mcsplat.data import load_scene
from mcsplat.data.attachments.depth import DepthOptions
from mcsplat.depth_supervision.correlation import DepthCorrelation, correlation_loss
from mcsplat.errors import MCSplatError
from mcsplat.features import FeatureStart
from mcsplat.gaussians import GaussianModel
from mcsplat.run.state import feature_parts
from mcsplat.train import train

from tests.support.device_reads import RefuseReads
from tests.support.helpers import views_a_term_spoke_on


def test_the_loss_ignores_scale_and_shift_and_pulls_the_shape():
    truth = torch.linspace(1.0, 3.0, 64).reshape(8, 8)
    keep = torch.ones(8, 8, dtype=torch.bool)
    assert float(correlation_loss(truth, 7.0 * truth + 2.0, keep)) == pytest.approx(0.0, abs=1e-6)
    assert float(correlation_loss(truth, 5.0 - truth, keep)) == pytest.approx(2.0, abs=1e-6)
    # A flat map says nothing, nor do too few pixels: 0 and no gradient, found without a read of the device.
    few = keep & (torch.arange(64).reshape(8, 8) < 10)
    for prior, kept in ((torch.full_like(truth, 4.0), keep), (truth, few), (truth, keep & False)):
        rendered = truth.clone().requires_grad_()
        with RefuseReads():
            nothing = correlation_loss(rendered, prior, kept)
            nothing.backward()
        assert float(nothing.detach()) == 0.0 and not rendered.grad.any()
    # Gradient descent on a noisy render brings its shape to the map's, whatever the map's scale and offset.
    rendered = (truth + 0.5 * torch.randn(8, 8, generator=torch.Generator().manual_seed(0))).requires_grad_()
    before = float(correlation_loss(rendered.detach(), 0.1 * truth + 30.0, keep))
    for _ in range(200):
        loss = correlation_loss(rendered, 0.1 * truth + 30.0, keep)
        loss.backward()
        with torch.no_grad():
            rendered -= 2.0 * rendered.grad
            rendered.grad = None
    assert before > 0.05 and float(correlation_loss(rendered.detach(), truth, keep)) < 0.01 * before


def _depth_folder(tmp_path: Path, scene, count: int) -> Path:
    """Depth maps rising left to right for the first `count` training views (a shape to correlate with)."""
    folder = tmp_path / "depths"
    folder.mkdir()
    for view in scene.train[:count]:
        ramp = np.linspace(2.0, 6.0, view.camera.width)[None, :].repeat(view.camera.height, axis=0)
        np.save(folder / f"{Path(view.name).name}.npy", ramp)
    return folder


def test_the_feature_is_a_group_of_options_that_hands_the_run_its_term(tmp_path, mini_demo):
    args = [str(mini_demo), "--depths", "some/where", "--depth-correlation", "0.2", "--depth-correlation-from", "0.1"]
    import tyro

    config = tyro.cli(COMMANDS["train"], args=args)
    assert (config.depth_prior.depth_correlation, config.depth_prior.depth_correlation_from) == (0.2, 0.1)
    saved = to_jsonable(config)  # config.json keeps the flags' names, beside the other options
    assert (saved["depth_correlation"], saved["depth_correlation_from"]) == (0.2, 0.1) and "depth_prior" not in saved
    with pytest.raises(MCSplatError, match="--depth-correlation-from 0.3: it shapes --depth-correlation"):
        config_of(data=mini_demo, depth_correlation_from=0.3, named=frozenset({"depth_correlation_from"}))
    with pytest.raises(MCSplatError, match="--depth-correlation inf: not a finite number"):
        config_of(data=mini_demo, depth_correlation=math.inf)

    bare = load_scene(mini_demo)
    scene = load_scene(mini_demo, attachments=[DepthOptions(str(_depth_folder(tmp_path, bare, 4)))])
    model = GaussianModel.random_init(1.0, blender=True, num_points=100, generator=torch.Generator().manual_seed(0))
    start = FeatureStart(scene, model, torch.device("cpu"), world_size=1)
    terms = feature_parts(config_of(data=mini_demo, depth_correlation=0.2), start).loss_terms
    assert [type(term) for term in terms] == [DepthCorrelation]
    assert feature_parts(config_of(data=mini_demo), start).loss_terms == []  # off: nothing added
    with pytest.raises(MCSplatError, match="none of the 12 training views has a depth map"):
        feature_parts(config_of(data=mini_demo, depth_correlation=0.2), FeatureStart(bare, model, start.device, 1))


def test_a_run_trains_with_it_on_the_views_that_have_maps(tmp_path, mini_demo, monkeypatch):
    folder = _depth_folder(tmp_path, load_scene(mini_demo), 6)
    given = views_a_term_spoke_on(monkeypatch, DepthCorrelation)
    metrics = train(config_of(data=mini_demo, out=tmp_path / "run", steps=40, quiet=True, lpips_net="alex",
                              save_every=0, save_renders=False, depths=str(folder), depth_correlation=0.5,
                              cap_max=1000))
    assert math.isfinite(metrics["psnr"])
    with_maps = {view.name for view in load_scene(mini_demo).train[:6]}
    assert any(any(values) for name, values in given.items() if name in with_maps)
    assert not any(any(values) for name, values in given.items() if name not in with_maps)
