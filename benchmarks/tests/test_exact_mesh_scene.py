"""The scene with an exact mesh (benchmarks/exact_mesh_scene.py) and the Chamfer distance (benchmarks/chamfer.py):
the scene loads as a Blender scene, the true mesh seen through the loaded cameras lands exactly on the pictures'
silhouettes, and the Chamfer figures are 0 for the truth itself and the known distance for moved copies."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image
from scipy.ndimage import binary_dilation

from mcsplat.data import Scene, load_scene
from mcsplat.mesh import read_mesh
from mcsplat.mesh.raster import rasterize

import chamfer
import exact_mesh_scene as exact

BENCHMARKS = Path(__file__).resolve().parents[1]

TRAIN, TEST, SIZE, VOXEL = 6, 2, 64, 0.025


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("exact") / "scene"
    exact.write_scene(folder, train=TRAIN, test=TEST, size=SIZE, voxel=VOXEL, supersample=2)
    return folder


@pytest.fixture(scope="module")
def scene(folder: Path) -> Scene:
    return load_scene(folder)


@pytest.fixture(scope="module")
def truth(folder: Path) -> trimesh.Trimesh:
    return read_mesh(folder / "mesh.ply")


def alpha_of(folder: Path, view) -> np.ndarray:
    """[H, W] alpha in [0, 1] of the view's PNG as written."""
    return np.asarray(Image.open(folder / f"{view.name}.png"))[..., 3] / 255.0


def test_scene_loads_as_blender(scene: Scene, folder: Path) -> None:
    assert scene.kind == "blender" and scene.alpha and scene.background == (1.0, 1.0, 1.0)
    assert (len(scene.train), len(scene.test)) == (TRAIN, TEST)
    assert {(v.camera.width, v.camera.height) for v in scene.train + scene.test} == {(SIZE, SIZE)}
    for view in scene.test:  # transparent pixels read as the white background, opaque ones as written
        written = np.asarray(Image.open(folder / f"{view.name}.png"))
        loaded = view.image.numpy()
        assert (loaded[written[..., 3] == 0] == 255).all()
        opaque = written[..., 3] == 255
        assert opaque.sum() > 0.1 * SIZE * SIZE and (loaded[opaque] == written[..., :3][opaque]).all()


def test_cameras_look_at_the_origin_upright(scene: Scene) -> None:
    """Blender's axes were written: the origin is at the image's centre, in front, and the world's up (+z) points up
    in every picture (image rows grow downwards)."""
    for view in scene.train + scene.test:
        camera = view.camera
        w2c = camera.world_to_camera.double()
        origin, above = w2c[:3, 3], w2c[:3, :3] @ torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64) + w2c[:3, 3]
        assert origin[2] > 0 and abs(origin[0]) < 1e-5 and abs(origin[1]) < 1e-5
        assert above[1] / above[2] < origin[1] / origin[2] - 0.05


def test_true_mesh_lands_on_the_silhouettes(scene: Scene, folder: Path, truth: trimesh.Trimesh) -> None:
    """The key check of the scene: the true mesh, drawn or projected with the cameras load_scene made from the json,
    covers the pictures' object and nothing else."""
    vertices, faces = torch.from_numpy(np.asarray(truth.vertices)), torch.from_numpy(np.asarray(truth.faces))
    for view in scene.train + scene.test:
        alpha = alpha_of(folder, view)
        drawn = (rasterize(vertices, faces, view.camera).face >= 0).numpy()
        shown = alpha >= 0.5
        assert (drawn & shown).sum() / (drawn | shown).sum() > 0.95  # 64 pixels: the rim weighs
        assert (alpha[drawn != shown] % 1 > 0).all()  # they differ only where a pixel is partly covered
        w2c = view.camera.world_to_camera.double().numpy()
        points = np.asarray(truth.vertices) @ w2c[:3, :3].T + w2c[:3, 3]
        u = points[:, 0] / points[:, 2] * view.camera.fx + view.camera.cx
        v = points[:, 1] / points[:, 2] * view.camera.fy + view.camera.cy
        assert ((u >= 0) & (u < SIZE) & (v >= 0) & (v < SIZE)).all()
        column, row = u.astype(int), v.astype(int)
        # Every vertex on the object's pixels grown by one (a rim vertex may fall on a sliver the samples missed),
        # and nearly all on the object's pixels themselves.
        assert binary_dilation(alpha > 0)[row, column].all()
        assert (alpha[row, column] > 0).mean() > 0.98


def test_the_splat_renderer_sees_the_same_silhouettes(scene: Scene, folder: Path, truth: trimesh.Trimesh) -> None:
    """The pictures come from the mesh rasterizer and the models are drawn by the splat renderer: the true surface as
    small opaque splats, drawn by render(), covers the same pixels, not a pixel off (so that a depth bias found with
    this scene is the model's, not a convention the two renderers disagree on)."""
    from mcsplat.render import Splats, render

    points, _ = trimesh.sample.sample_surface(truth, 60_000, seed=0)
    count = len(points)
    quats = torch.zeros(count, 4)
    quats[:, 0] = 1.0
    splats = Splats(means=torch.tensor(points, dtype=torch.float32), quats=quats,
                    scales=torch.full((count, 3), 0.004), opacities=torch.full((count,), 0.99),
                    sh=torch.zeros(count, 1, 3))
    for view in scene.test:
        drawn = render(splats, view.camera, None, 0, eps2d=0.0).alpha.detach().numpy() > 0.5
        shown = alpha_of(folder, view) >= 0.5
        assert (drawn & shown).sum() / (drawn | shown).sum() > 0.9
        rows, columns = np.nonzero(drawn)
        rows_shown, columns_shown = np.nonzero(shown)
        assert abs(columns.mean() - columns_shown.mean()) < 0.25 and abs(rows.mean() - rows_shown.mean()) < 0.25


def test_true_mesh_is_the_shape(folder: Path, truth: trimesh.Trimesh) -> None:
    """mesh.ply is closed, faces outwards, lies on the formulas' zero set and carries the texture's colours."""
    assert truth.is_watertight and truth.volume > 0
    off = np.abs(exact.signed_distance(np.asarray(truth.vertices)))
    assert np.median(off) < 0.02 * VOXEL and off.max() < 0.5 * VOXEL
    expected = np.round(exact.texture(np.asarray(truth.vertices)) * 255)
    assert np.array_equal(np.asarray(truth.visual.vertex_colors)[:, :3], expected)


def test_chamfer_of_the_truth_is_zero(truth: trimesh.Trimesh) -> None:
    figures = chamfer.chamfer(truth, truth, samples=20_000)
    assert figures["chamfer_mean"] < 1e-9 and figures["accuracy_within"] == figures["completeness_within"] == 1.0
    assert abs(figures["offset_median"]) < 1e-9
    assert figures["f_score"] == 1.0 and figures["diagonal"] == pytest.approx(np.linalg.norm(truth.extents))


def test_chamfer_of_a_grown_sphere_is_the_growth() -> None:
    """A sphere 0.02 larger than another lies 0.02 from it everywhere: both directions measure it."""
    small, large = trimesh.creation.icosphere(5, 0.5), trimesh.creation.icosphere(5, 0.52)
    figures = chamfer.chamfer(large, small, samples=20_000)
    for key in ("accuracy_median", "accuracy_mean", "completeness_median", "completeness_mean", "chamfer_mean"):
        assert figures[key] == pytest.approx(0.02, rel=0.02)
    assert figures["chamfer_mean_pct"] == pytest.approx(100 * 0.02 / np.linalg.norm(small.extents), rel=0.02)
    assert figures["offset_median"] == pytest.approx(0.02, rel=0.02)  # outside the truth
    assert chamfer.chamfer(small, large, samples=20_000)["offset_median"] == pytest.approx(-0.02, rel=0.02)


def test_chamfer_of_a_shifted_copy(truth: trimesh.Trimesh) -> None:
    """A copy moved by d along x: no point is farther than d from the other surface, in both directions; a sphere's
    points are d |cos| away, d/2 on average; the scene's faces parallel to x stay on each other (distance 0)."""
    d = 0.02
    sphere = trimesh.creation.icosphere(5, 0.5)
    figures = chamfer.chamfer(sphere.copy().apply_translation([d, 0, 0]), sphere, samples=20_000)
    assert figures["accuracy_mean"] == pytest.approx(d / 2, rel=0.03)
    assert figures["completeness_mean"] == pytest.approx(d / 2, rel=0.03)
    moved = truth.copy().apply_translation([d, 0, 0])
    samples = chamfer.surface_samples(moved, 20_000, seed=0)
    assert chamfer.to_surface(samples, truth).max() <= d * (1 + 1e-6)
    figures = chamfer.chamfer(moved, truth, samples=20_000)
    for name in ("accuracy", "completeness"):
        assert 0.1 * d < figures[f"{name}_mean"] < d and figures[f"{name}_within"] < 1


def test_missing_half_costs_completeness_only(truth: trimesh.Trimesh) -> None:
    """Accuracy and completeness are not swapped: half of the truth is all accurate and half complete."""
    half = truth.submesh([np.nonzero(truth.triangles_center[:, 0] < 0)[0]], append=True)
    figures = chamfer.chamfer(half, truth, samples=20_000)
    assert figures["accuracy_mean"] < 1e-9 and figures["accuracy_within"] == 1.0
    assert 0.35 < figures["completeness_within"] < 0.65 and figures["completeness_mean"] > 0.05


def test_refuses_a_folder_that_holds_files(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(exact.SceneError, match="not an empty folder"):
        exact.write_scene(tmp_path, train=1, test=0, size=8, voxel=0.05, supersample=1)
    done = subprocess.run([sys.executable, str(BENCHMARKS / "exact_mesh_scene.py"), str(tmp_path)],
                          capture_output=True, text=True)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and "not an empty folder" in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
