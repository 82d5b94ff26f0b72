"""Depth supervision (depth_supervision/terms.py): the terms move the rendered depth onto a known plane and sphere,
relative and disparity maps are read up to scale and shift, metric maps in the wrong units are refused, views without
depth give nothing, and the SfM points each COLMAP image saw are read and projected as the image saw them."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mcsplat.camera import Camera, intrinsics
from mcsplat.config import config_of
from mcsplat.data import View, load_scene
from mcsplat.data.attachments.depth import KIND as DEPTH
from mcsplat.data.attachments.depth import DepthOptions
from mcsplat.data.attachments.kind import Attachment
from mcsplat.data.sfm_tracks import points_seen
from mcsplat.depth_supervision.terms import (DenseDepth, DepthTermOptions, Schedule, SparseDepth, check_metric_scale,
                                             depth_terms, project, target_depth)
from mcsplat.errors import MCSplatError
from mcsplat.gaussians import GaussianModel
from mcsplat.loss_terms import StepContext
from mcsplat.render import render
from mcsplat.train import train

from tests.support.device_reads import RefuseReads
from tests.support.helpers import views_a_term_spoke_on

W, H = 32, 24
CAMERA = Camera(K=intrinsics(30.0, 30.0, W / 2, H / 2), world_to_camera=torch.eye(4), width=W, height=H)


def pixel_rays() -> torch.Tensor:
    """[H, W, 3] each pixel centre's ray (x, y, 1) in the camera (= the world here)."""
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    return torch.stack([(u - W / 2) / 30.0, (v - H / 2) / 30.0, torch.ones_like(u)], dim=-1)


def plane_depth() -> torch.Tensor:
    """z of the tilted plane z = 2 + 0.5 x met by each pixel's ray."""
    rays = pixel_rays()
    return 2.0 / (1.0 - 0.5 * rays[..., 0])


def sphere_depth(centre=(0.0, 0.0, 4.0), radius=1.2) -> torch.Tensor:
    """z where each pixel's ray first meets the sphere, 0 where it misses."""
    rays = pixel_rays()
    c = torch.tensor(centre)
    b = (rays * c).sum(-1)
    a = (rays * rays).sum(-1)
    disc = b * b - a * (c @ c - radius ** 2)
    t = (b - disc.clamp_min(0).sqrt()) / a
    return torch.where(disc > 0, t, torch.zeros_like(t))


def sheet(depth: float = 3.0, count: int = 14, tilt: float = 0.0) -> GaussianModel:
    """Opaque round Gaussians on a grid filling the view at `depth` (plus `tilt` times x)."""
    xs = torch.linspace(-0.6, 0.6, count) * depth
    ys = torch.linspace(-0.45, 0.45, count) * depth
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    n = grid.shape[0]
    means = torch.cat([grid, depth + tilt * grid[:, :1]], dim=1)
    return GaussianModel(means=means, log_scales=torch.full((n, 3), math.log(0.12 * depth / 3)),
                         quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), opacity_logits=torch.full((n,), 3.0),
                         sh0=torch.full((n, 1, 3), 0.5), shN=torch.zeros(n, 15, 3))


def view_with(depth: torch.Tensor | None, name: str = "v") -> View:
    attachments = {} if depth is None else {"depth": Attachment(DEPTH, depth.float())}
    return View(CAMERA, torch.zeros(H, W, 3, dtype=torch.uint8), name, attachments=attachments)


def context(model: GaussianModel, view: View, step: int = 0, steps: int = 100) -> StepContext:
    result = render(model, view.camera)
    return StepContext(step, view, 0, view.camera, result.rgb, torch.zeros(H, W, 3), None, model, result, steps)


def fit(model: GaussianModel, term, view: View, steps: int = 150) -> torch.Tensor:
    """Adam on the means alone against `term`; the rendered depth at the end."""
    optimizer = torch.optim.Adam([model.params["means"]], lr=0.01)
    for _ in range(steps):
        loss = term(context(model, view))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        return render(model, view.camera).depth


def test_the_dense_term_moves_a_sheet_onto_a_plane_and_a_sphere():
    for truth, start in ((plane_depth(), 3.0), (sphere_depth(), 5.0)):
        model = sheet(start)
        term = DenseDepth("metric", Schedule(1.0))
        known = truth > 0
        before = render(model, CAMERA).depth.detach()
        first = term(context(model, view_with(truth)))
        first.backward()
        # Where the sheet is behind the surface the gradient pushes the Gaussians nearer (descent lowers z).
        assert float(model.params["means"].grad[:, 2].sum()) > 0
        depth = fit(model, term, view_with(truth))
        error_before = ((before - truth).abs() / truth)[known].median()
        error_after = ((depth - truth).abs() / truth)[known].median()
        assert error_before > 0.2 and error_after < 0.03, (float(error_before), float(error_after))


def test_the_sparse_term_moves_the_depth_at_its_points_onto_the_plane():
    g = torch.Generator().manual_seed(0)
    u, v = torch.rand(60, generator=g) * (W - 8) + 4, torch.rand(60, generator=g) * (H - 8) + 4
    x, y = (u - W / 2) / 30.0, (v - H / 2) / 30.0
    z = 2.0 / (1.0 - 0.5 * x)  # on the plane z = 2 + 0.5 X
    points = torch.stack([x * z, y * z, z], dim=1)
    behind = torch.tensor([[0.0, 0.0, -2.0], [50.0, 0.0, 2.0]])  # behind the camera, outside the image: ignored
    term = SparseDepth({"v": torch.cat([points, behind])}, Schedule(1.0))
    pu, pv, pz = project(torch.cat([points, behind]), CAMERA)
    torch.testing.assert_close(torch.stack([pu, pv, pz]), torch.stack([u, v, z]))
    model = sheet(3.0)
    term(context(model, view_with(None))).backward()
    assert float(model.params["means"].grad[:, 2].sum()) > 0, "the sheet behind the points is pulled nearer"
    depth = fit(model, term, view_with(None), steps=150)
    sampled = torch.nn.functional.grid_sample(depth[None, None], torch.stack([2 * u / W - 1, 2 * v / H - 1], -1)
                                              [None, None], align_corners=False)[0, 0, 0]
    assert ((sampled - z).abs() / z).median() < 0.03
    assert term(context(model, view_with(None, name="no points"))) is None


def test_the_sparse_term_leaves_out_the_points_a_mask_leaves_out():
    """A point on pixels the view's mask leaves out (a passer-by, the sky) says nothing about the depth there."""
    model = sheet(3.0)
    near = torch.tensor([[-0.5, 0.0, 2.0], [0.5, 0.0, 2.5]])  # the left point on kept pixels, the right one masked
    keep = torch.ones(H, W, 1)
    keep[:, W // 2:] = 0.0
    term = SparseDepth({"v": near}, Schedule(1.0))
    ctx = context(model, view_with(None))
    masked = StepContext(ctx.step, ctx.view, 0, ctx.camera, ctx.rgb, ctx.target, keep, model, ctx.result, ctx.steps)
    alone = SparseDepth({"v": near[:1]}, Schedule(1.0))(ctx)
    torch.testing.assert_close(term(masked), alone)
    assert abs(float(term(ctx).detach()) - float(alone.detach())) > 0.05, "unmasked, the right point counts"
    keep[:] = 0.0
    model.params["means"].grad = None
    nothing = term(masked)
    nothing.backward()
    assert float(nothing.detach()) == 0.0 and not model.params["means"].grad.any(), "every point masked: nothing to say"


def test_the_sparse_term_reads_nothing_back_from_the_device():
    """The term's value and gradient are made without a read of the device (a count of the points in view, a check
    that some weigh): on a GPU each would make the host wait, and a CUDA graph could not hold it. Points outside the
    view (behind the camera, beside the image) weigh nothing instead of being left out by a boolean mask."""
    model = sheet(3.0)
    points = torch.tensor([[-0.5, 0.0, 2.0], [0.5, 0.2, 2.5], [0.0, 0.0, -2.0], [50.0, 0.0, 2.0]])
    term = SparseDepth({"v": points}, Schedule(1.0))
    ctx = context(model, view_with(None))
    with RefuseReads():
        value = term(ctx)
        value.backward()
    in_view = SparseDepth({"v": points[:2]}, Schedule(1.0))(context(model, view_with(None)))
    torch.testing.assert_close(value.detach(), in_view.detach())
    assert torch.isfinite(model.params["means"].grad).all() and model.params["means"].grad.any()


def test_a_map_that_fits_only_inverted_is_left_out_with_a_warning():
    """Disparity maps given as relative depth fit the render only with a negative scale: the term says so and adds
    nothing, rather than training toward the inverted shape."""
    model = sheet(3.0, tilt=0.4)
    rendered = context(model, view_with(None)).result.depth.detach()
    disparity = torch.where(rendered > 0, 1.0 / rendered.clamp_min(1e-6), torch.zeros_like(rendered))
    with pytest.warns(RuntimeWarning, match="only inverted.*--depth-loss disparity"):
        assert DenseDepth("relative", Schedule(1.0))(context(model, view_with(disparity))) is None


def test_relative_and_disparity_maps_are_read_up_to_scale_and_shift():
    model = sheet(3.0, tilt=0.4)
    ctx = context(model, view_with(None))
    rendered = ctx.result.depth.detach()
    valid = (ctx.result.alpha > 0.5).float()
    for mode, prior in (("relative", 7.0 * rendered + 0.3), ("disparity", 7.0 / rendered + 0.3)):
        prior = torch.where(valid > 0, prior, torch.zeros_like(prior))
        value = DenseDepth(mode, Schedule(1.0))(context(model, view_with(prior)))
        assert value.item() < 1e-4, (mode, value.item())
        torch.testing.assert_close(target_depth(mode, prior, rendered, valid)[valid > 0], rendered[valid > 0])
    # The same map taken as metric is far off; a map of another shape is off in any mode.
    assert float(DenseDepth("metric", Schedule(1.0))(context(model, view_with(7.0 * rendered + 0.3))).detach()) > 0.8
    bumpy = rendered * (1 + 0.3 * torch.sin(torch.arange(W) / 2.0))
    assert float(DenseDepth("relative", Schedule(1.0))(context(model, view_with(bumpy))).detach()) > 0.02


def test_metric_maps_in_the_wrong_units_are_refused_in_one_line():
    model = sheet(3.0)
    truth = plane_depth()
    check_metric_scale([view_with(truth)], model.means)  # the scene's units: accepted
    with pytest.raises(MCSplatError, match="millimetres of a scene in metres") as error:
        check_metric_scale([view_with(truth * 1000)], model.means)
    assert "\n" not in str(error.value) and "--depth-png-step" in str(error.value)
    with pytest.raises(MCSplatError, match="metres of a scene in millimetres"):
        check_metric_scale([view_with(truth / 1000)], model.means)


def test_the_weight_starts_at_its_share_and_falls_to_its_final_share():
    schedule = Schedule(0.2, start=0.25, final=0.5)
    assert schedule.at(24, 101) == 0.0
    assert schedule.at(26, 101) == pytest.approx(0.2, rel=0.02)
    assert schedule.at(100, 101) == pytest.approx(0.1)
    model = sheet(3.0)
    assert DenseDepth("metric", schedule)(context(model, view_with(plane_depth()), step=10, steps=101)) is None


def test_sparse_depth_starts_half_way_and_fades_out_by_default():
    """The default benchmarks/sparse_depth.py chose: the photos have the last steps to themselves."""
    schedule = DepthTermOptions(sparse_depth=0.1).sparse_schedule
    assert schedule.at(999, 2000) == 0.0
    assert schedule.at(1000, 2000) == pytest.approx(0.1)
    assert schedule.at(1500, 2000) == pytest.approx(0.05, rel=0.01)
    assert schedule.at(1999, 2000) == 0.0


def test_the_options_refuse_what_they_cannot_use():
    with pytest.raises(MCSplatError, match="--depths is 'none'"):
        config_of(data=Path("."), depth_loss="metric")
    with pytest.raises(MCSplatError, match="--depth-weight 0.5: these shape a depth term"):
        config_of(data=Path("."), depth_weight=0.5, named=frozenset({"depth_weight"}))
    with pytest.raises(MCSplatError, match="--sparse-depth-from 0.5"):
        config_of(data=Path("."), sparse_depth_from=0.5, named=frozenset({"sparse_depth_from"}))
    config_of(data=Path("."), sparse_depth=0.1, sparse_depth_from=0.5, named=frozenset({"sparse_depth_from"}))


def test_a_scene_with_depth_maps_for_some_views_trains(tmp_path, mini_demo, monkeypatch):
    """Half the training views have a map; the others give no depth term; --sparse-depth is refused on a scene
    without tracks."""
    folder = tmp_path / "depths"
    folder.mkdir()
    scene = load_scene(mini_demo)
    for view in scene.train[:6]:
        np.save(folder / f"{Path(view.name).name}.npy", np.full((view.camera.height, view.camera.width), 4.0))
    scene = load_scene(mini_demo, attachments=[DepthOptions(str(folder))])
    term = DenseDepth("relative", Schedule(1.0))
    assert [("depth" in view.attachments) for view in scene.train] == [True] * 6 + [False] * 6
    model = sheet(3.0)
    ctx = context(model, view_with(None))
    assert term(StepContext(0, scene.train[8], 8, CAMERA, ctx.rgb, ctx.target, None, model, ctx.result, 10)) is None
    with pytest.raises(MCSplatError, match="needs a COLMAP scene"):
        depth_terms(scene, model.means, "cpu", sparse=Schedule(0.1), mode="none", dense=Schedule(0.1))
    given = views_a_term_spoke_on(monkeypatch, DenseDepth)
    metrics = train(config_of(data=mini_demo, out=tmp_path / "run", steps=40, quiet=True, lpips_net="alex",
                                save_every=0, save_renders=False, depths=str(folder), depth_loss="metric",
                                depth_weight=0.5, cap_max=1000))
    assert math.isfinite(metrics["psnr"])
    with_maps = {view.name for view in scene.train[:6]}
    assert not any(any(values) for name, values in given.items() if name not in with_maps)
    assert any(any(values) for name, values in given.items() if name in with_maps)


def test_the_sfm_points_each_cup_image_saw_are_read_and_projected(shared_data):
    pycolmap = pytest.importorskip("pycolmap")
    root = shared_data / "colmap_cup"
    seen = points_seen(root)
    reconstruction = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    scene = load_scene(root, downscale=4)
    # Each point once per image (an image may observe one point through two keypoints).
    assert len(seen) == 77 and sum(len(points) for points in seen.values()) == sum(
        len({p.point3D_id for p in image.points2D if p.has_point3D()}) for image in reconstruction.images.values())
    for image in list(reconstruction.images.values())[:3]:
        ids = sorted({p.point3D_id for p in image.points2D if p.has_point3D()})
        name = image.name.rsplit(".", 1)[0]
        assert len(seen[name]) == len(ids)
        expected = np.array([reconstruction.points3D[i].xyz for i in ids])
        np.testing.assert_allclose(np.sort(seen[name], axis=0), np.sort(expected, axis=0))
        # Projected with the loaded view's camera at half its size, as a coarse-to-fine step renders it, the points
        # land where COLMAP's camera puts them (its pixels scaled to the step's size) at COLMAP's z.
        view = next(v for v in scene.train + scene.test if v.name == name)
        camera = view.camera_at(0.5)
        u, v, z = project(torch.from_numpy(seen[name]).float(), camera)
        local = np.array([image.cam_from_world() * x for x in seen[name]])
        pixels = np.array([image.camera.img_from_cam(p) for p in local])
        inside = local[:, 2] > 0
        scale = np.array([camera.width / image.camera.width, camera.height / image.camera.height])
        pixels = pixels[inside] * scale
        inside_image = (pixels >= 0).all(1) & (pixels < [camera.width, camera.height]).all(1)
        assert len(z) == inside_image.sum() > 100
        np.testing.assert_allclose(torch.stack([u, v], 1).numpy(), pixels[inside_image], atol=2e-3)
        np.testing.assert_allclose(z.numpy(), local[inside][inside_image, 2], rtol=1e-5)
