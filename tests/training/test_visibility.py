"""Gaussians that contribute nothing visible: found exactly, counted at the end of training, left out by
`mcsplat export --prune` without changing what the training views show."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import torch

from mcsplat.cli import main
from mcsplat.data import load_scene
from mcsplat.gaussians import PARAM_KEYS, GaussianModel
from mcsplat.io.ply import read_ply
from mcsplat.render import render
from mcsplat.run.trained import load
from mcsplat.visibility import count_invisible, seen_in

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"


def with_hidden_extras(model: GaussianModel) -> GaussianModel:
    """The model plus two Gaussians no camera can see: one far outside every view, one too faint (opacity 0.003 <
    1/255) at the centre of the object, where every camera looks."""
    extra = model.subset(torch.arange(2))
    with torch.no_grad():
        extra.params["means"][0] = torch.tensor([50.0, 50.0, 50.0])
        extra.params["means"][1] = torch.zeros(3)
        extra.params["log_scales"][1] = math.log(0.3)
        extra.params["opacity_logits"][1] = math.log(0.003 / 0.997)
    return GaussianModel(**{key: torch.cat([model.params[key].detach(), extra.params[key].detach()])
                            for key in PARAM_KEYS})


def test_unseen_gaussians_are_found_and_leaving_them_out_changes_no_training_view(tiny_run):
    trained = load(tiny_run, torch.device("cpu")).model
    model = with_hidden_extras(trained)
    scene = load_scene(DEMO)
    seen = seen_in(model, scene.train, scene.background, torch.device("cpu"))
    assert not seen[-2:].any(), "neither the far nor the faint Gaussian is composited anywhere"
    assert seen[:-2].sum() > 0.5 * trained.num_gaussians
    counts = count_invisible(model, seen)
    assert counts.total == model.num_gaussians and counts.unseen == int((~seen).sum())
    assert counts.faint == int((model.opacities < 1 / 255).sum()) >= 1

    pruned = model.subset(seen)
    for view in scene.train[::20]:
        with torch.no_grad():
            full = render(model, view.camera, scene.background, 3).rgb
            kept = render(pruned, view.camera, scene.background, 3).rgb
        assert torch.allclose(kept, full, atol=1e-6), view.name


def test_training_counts_them_and_export_prune_leaves_them_out(tiny_run, tmp_path, capsys):
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    invisible = metrics["invisible_gaussians"]
    assert invisible["total"] == metrics["num_gaussians"]
    assert 0 <= invisible["opacity_below_1_255"] <= invisible["never_composited"] < invisible["total"]

    out = tmp_path / "pruned.ply"
    assert main(["export", str(tiny_run), "--prune", "--out", str(out), "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    assert f"{invisible['never_composited']:,} of {invisible['total']:,} Gaussians contribute nothing" in printed
    full, kept = map(float, re.search(r"test PSNR on 25 views: ([\d.]+) dB with every Gaussian, ([\d.]+) dB",
                                      printed).groups())
    assert abs(kept - full) <= 0.05, printed

    model = load(tiny_run, torch.device("cpu")).model
    scene = load_scene(DEMO)
    expected = seen_in(model, scene.train, scene.background, torch.device("cpu")) & (model.opacities > 0.005)
    written = read_ply(out)
    assert written["means"].shape[0] == int(expected.sum())
    assert torch.equal(written["means"], model.means.detach()[expected])
