"""The live viewer in a real browser (headless Chromium over the DevTools protocol): the image the browser shows is
our render of its camera within JPEG error, the pause button stops the step counter, the page and the report load
with no network; and without viser, --viewer says how to install it.

The browser test skips, with the reason, where viser or a headless Chromium is missing (.ci/run installs both)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from mcsplat.cli import main
from mcsplat.config import ModelConfig, TrainConfig, config_of
from mcsplat.errors import MCSplatError
from mcsplat.run.events import Control
from mcsplat.strategy.mcmc import MCMCConfig
from mcsplat.train import standard_subscribers, train

DEMO = Path(__file__).resolve().parents[2] / "data" / "lego_demo"
SCREENSHOTS = os.environ.get("MCSPLAT_SCREENSHOTS")  # a folder: also save screenshots there (docs/ is made so)


def test_viewer_without_viser_says_how_to_install(tmp_path, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "viser" else find_spec(name, *a))
    with pytest.raises(MCSplatError, match=r"pip install 'mcsplat\[viewer\]'"):
        train(config_of(data=DEMO, out=tmp_path / "run", steps=5, quiet=True, viewer=True))
    assert not (tmp_path / "run").exists(), "a missing extra must not leave a half-started run"


def test_viewer_option_adds_the_viewer_subscriber(tmp_path):
    pytest.importorskip("viser")
    from mcsplat.viewer import TrainingViewer

    config = config_of(data=DEMO, out=tmp_path, viewer=True, port=9999)
    viewers = [s for s in standard_subscribers(config, tmp_path) if isinstance(s, TrainingViewer)]
    assert len(viewers) == 1 and (viewers[0].host, viewers[0].port) == ("127.0.0.1", 9999)
    assert not any(isinstance(s, TrainingViewer) for s in standard_subscribers(TrainConfig(data=DEMO), tmp_path))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def browser():
    pytest.importorskip("viser", reason="the viewer's optional dependency viser is not installed")
    from tests.support.browser import Browser, find_browser

    if find_browser() is None:
        pytest.skip("no headless Chromium: apt-get install chromium-headless-shell (.ci/run does so on CI)")
    b = Browser(width=800, height=600)
    try:
        b.call("Network.enable")
        yield b
    finally:
        b.close()


def click(browser, text: str) -> None:
    """Click the button (or checkbox of the label) whose text is `text`, as a user would."""
    assert browser.evaluate(f"""(() => {{
        for (const el of document.querySelectorAll('button, label')) {{
            if (el.textContent.trim() === {text!r}) {{
                const target = el.tagName === 'LABEL' ? (el.control || el.parentElement.querySelector('input'))
                                                      : el;
                if (target) {{ target.click(); return true; }}
            }}
        }}
        const box = [...document.querySelectorAll('input[type=checkbox]')].find(
            i => i.closest('div').parentElement.textContent.includes({text!r}));
        if (box) {{ box.click(); return true; }}
        return false; }})()"""), f"no {text!r} control on the page"


def shown_step(browser) -> int:
    text = browser.evaluate("document.body.innerText")
    found = re.search(r"step\s+([\d,]+)\s*/", text)
    assert found, text
    return int(found.group(1).replace(",", ""))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-12)))


def test_live_viewer_in_a_browser_and_the_report(browser, tiny_run, tmp_path):
    from mcsplat.viewer import TrainingViewer
    from mcsplat.viewer.cameras import camera_from_pose

    viewer, control = TrainingViewer(port=free_port(), quiet=True), Control()
    config = TrainConfig(data=DEMO, out=tmp_path / "live", steps=100_000, quiet=True, save_every=0, eval_every=0,
                         model=ModelConfig(num_init_points=2000), mcmc=MCMCConfig(cap_max=3000, refine_start=50),
                         scale_schedule=False)
    failure: list[BaseException] = []

    def run() -> None:
        try:
            train(config, subscribers=[viewer], control=control)
        except MCSplatError as error:
            if "stopped at step" not in str(error):
                failure.append(error)
        except BaseException as error:  # shown by the assertion below
            failure.append(error)

    trainer = threading.Thread(target=run, daemon=True)
    trainer.start()
    try:
        deadline = time.monotonic() + 60
        while viewer.server is None and time.monotonic() < deadline and not failure:
            time.sleep(0.1)
        assert viewer.server is not None, failure
        browser.call("Page.navigate", url=viewer.server.url)
        browser.wait_for("document.body.innerText.includes('steps/s')", timeout=60)

        # Pause: the step counter on the page stops, and so does the run.
        click(browser, "Pause training")
        browser.wait_for("document.body.innerText.includes('Resume training')")
        time.sleep(0.5)  # the step under way ends, its numbers reach the page
        paused_at = shown_step(browser)
        time.sleep(1.5)
        assert shown_step(browser) == paused_at and control.paused
        assert viewer.step == paused_at

        # The browser's image is our render of the browser's camera (the frustums hidden, the model still).
        click(browser, "Training cameras")
        deadline = time.monotonic() + 20
        while not all(not f.visible for f in viewer.server.frustums) and time.monotonic() < deadline:
            time.sleep(0.1)
        renderers = list(viewer.server.renderers.values())
        assert renderers, "the page connected no client"
        time.sleep(1.0)  # the full-resolution image after the settle time
        for renderer in renderers:
            camera = renderer.client.camera
            width, height = camera.image_width, camera.image_height
            shown = renderer.client.get_render(height, width, timeout=60)[..., :3]
            ours = viewer.server.render(camera_from_pose(camera.wxyz, camera.position, camera.fov, width, height))
            assert shown.shape == ours.shape
            print(f"browser vs our render: {psnr(shown, ours):.1f} dB at {width}x{height}")
            assert psnr(shown, ours) > 30.0, "the browser must show our render, up to JPEG compression"
            assert psnr(shown, np.full_like(ours, 255)) < 25.0, "and not an empty page"
        if SCREENSHOTS:
            click(browser, "Training cameras")
            time.sleep(1.5)
            browser.screenshot(Path(SCREENSHOTS) / "viewer.png")

        click(browser, "Resume training")
        browser.wait_for(f"(document.body.innerText.match(/step\\s+([\\d,]+)/) || ['', '0'])[1]"
                         f".replace(/,/g, '') > {paused_at + 5}", timeout=60)
        local = [u for u in browser.requested_urls() if not u.startswith(("data:", "blob:", "about:"))]
        assert local and all(u.startswith(viewer.server.url) for u in local), "the page needs no network"
    finally:
        control.stop()
        trainer.join(timeout=120)
    assert not trainer.is_alive() and not failure, failure
    assert viewer.server is None, "the viewer closes with the run"

    # The report opens in the browser and every image decodes.
    browser.call("Page.navigate", url=(tiny_run / "report.html").as_uri())
    browser.wait_for("document.readyState === 'complete'")
    decoded = browser.evaluate("Promise.all([...document.images].map(i => i.decode().then(() => i.naturalWidth)))")
    assert len(decoded) == 7 and min(decoded) > 100
    if SCREENSHOTS:
        browser.screenshot(Path(SCREENSHOTS) / "report.png")


def test_render_modes_of_the_viewer(tiny_run):
    from mcsplat.run.trained import load
    from mcsplat.viewer.modes import MODES, render_mode

    from mcsplat.data import load_scene

    model = load(tiny_run, torch.device("cpu")).model
    camera = load_scene(DEMO).test[0].camera
    images = {mode: render_mode(model, camera, mode, (1.0, 1.0, 1.0), 3, 1.0) for mode in MODES}
    assert all(image.shape == (camera.height, camera.width, 3) and image.dtype == np.uint8
               for image in images.values())
    with torch.no_grad():
        from mcsplat.render import render
        expected = render(model, camera, (1.0, 1.0, 1.0), 3)
    assert np.array_equal(images["RGB"], (expected.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy())
    covered = expected.alpha.numpy() > 0.5
    assert (images["alpha"][covered] > 127).all() and (images["alpha"][~covered] <= 128).all()
    assert images["depth"][covered].mean() > 20 and images["depth"][expected.alpha.numpy() < 0.05].max() == 0
    # Centres: small opaque dots, so far less of the image is covered than by the Gaussians themselves.
    dots = (images["centres"] < 250).any(axis=2).mean()
    assert 0.0 < dots < (images["RGB"] < 250).any(axis=2).mean()


def test_a_mesh_in_a_browser(browser, tmp_path):
    """`mcsplat view mesh.ply`: the page draws the mesh itself, in its vertex colours (a red ball on white)."""
    import trimesh
    from PIL import Image

    from mcsplat.mesh import write_mesh
    from mcsplat.viewer.saved import serve_mesh

    ball = trimesh.creation.icosphere(subdivisions=3)
    ball.visual.vertex_colors = np.tile([220, 30, 30, 255], (len(ball.vertices), 1)).astype(np.uint8)
    write_mesh(tmp_path / "ball.ply", ball)
    server, _ = serve_mesh(tmp_path / "ball.ply", "127.0.0.1", free_port(), quiet=True)
    try:
        browser.call("Page.navigate", url=server.url)
        browser.wait_for("document.body.innerText.includes('faces')", timeout=60)
        time.sleep(2.0)  # the mesh arrives and is drawn
        browser.screenshot(tmp_path / "page.png")
    finally:
        server.close()
    pixels = np.asarray(Image.open(tmp_path / "page.png").convert("RGB")).astype(int)
    red = (pixels[..., 0] > 100) & (pixels[..., 0] > pixels[..., 1] + 60)
    assert red.mean() > 0.02, f"the red ball covers {red.mean():.1%} of the page"


@pytest.fixture
def saved_viewer(tiny_run):
    """`mcsplat view RUN` on a free port, in a thread, stopped by the test."""
    pytest.importorskip("viser")
    from mcsplat.viewer.saved import view_saved

    port, stop = free_port(), threading.Event()
    thread = threading.Thread(target=view_saved, args=(tiny_run, "127.0.0.1", port, torch.device("cpu"), stop, True),
                              daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            time.sleep(0.2)
    try:
        yield port
    finally:
        stop.set()
        thread.join(timeout=30)


def test_the_viewer_accepts_its_own_page_only(saved_viewer):
    """A web page of another site, open in the same browser, must not read the scene through the WebSocket."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    port = saved_viewer
    url = f"ws://127.0.0.1:{port}"
    for origin in ("https://evil.example", f"http://rebinding.example:{port}", f"http://192.0.2.7:{port}"):
        with pytest.raises(InvalidStatus) as refused:
            connect(url, origin=origin, open_timeout=20).close()
        assert refused.value.response.status_code == 403, origin
    for origin in (None, f"http://127.0.0.1:{port}", f"http://localhost:{port}", "http://localhost:9000"):
        connect(url, origin=origin, open_timeout=20).close()  # its own page (or through an SSH tunnel), or no browser


def test_origin_rules_for_a_viewer_on_the_network():
    from mcsplat.viewer.access import OriginPolicy

    everywhere = OriginPolicy("0.0.0.0", allowed=["myhost.lan"])
    assert everywhere.accepts("http://192.168.1.5:8080", "192.168.1.5:8080", 8080), "the address the user typed"
    assert not everywhere.accepts("http://evil.example:8080", "evil.example:8080", 8080), "a name may rebind"
    assert not everywhere.accepts("http://192.168.1.9:8080", "192.168.1.5:8080", 8080), "another machine's page"
    assert everywhere.accepts("http://myhost.lan:8080", "myhost.lan:8080", 8080), "--viewer-origin"
    named = OriginPolicy("myhost.lan")
    assert named.accepts("http://myhost.lan:8080", "myhost.lan:8080", 8080) and \
        not named.accepts("http://myhost.lan:9999", "myhost.lan:8080", 8080)


def test_a_bad_port_or_host_is_one_line_not_a_hang(tiny_run, tmp_path):
    pytest.importorskip("viser")
    cases = [(["view", str(tiny_run), "--port", "70000"], "--port 70000"),
             (["view", str(tiny_run), "--host", "192.0.2.1"], "--host 192.0.2.1: cannot listen there"),
             (["view", str(tiny_run), "--host", "no-such-host.invalid"], "--host no-such-host.invalid: not a known"),
             (["train", str(DEMO), "--out", str(tmp_path / "run"), "--viewer", "--port", "-1"], "--port -1")]
    # In one process, whose alarm ends it if a command hangs instead of failing (what viser does with these).
    script = ("import json, signal, sys; signal.alarm(60); from mcsplat.cli import main; "
              "print(json.dumps([main(args) for args in json.loads(sys.argv[1])]))")
    done = subprocess.run([sys.executable, "-c", script, json.dumps([args for args, _ in cases])],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and json.loads(done.stdout) == [2] * len(cases), done.stderr[-2000:]
    errors = done.stderr.splitlines()
    assert len(errors) == len(cases), errors
    for error, (_, expected) in zip(errors, cases):
        assert error.startswith(f"mcsplat: error: {expected}"), error
    assert not (tmp_path / "run").exists()


def test_a_ply_without_gaussians_is_one_line(tmp_path, capsys):
    pytest.importorskip("viser")
    from plyfile import PlyData, PlyElement

    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
             "rot_2", "rot_3"]
    empty = np.empty(0, dtype=[(name, "f4") for name in names])
    PlyData([PlyElement.describe(empty, "vertex")]).write(str(tmp_path / "empty.ply"))
    assert main(["view", str(tmp_path / "empty.ply"), "--port", str(free_port())]) == 2
    error = capsys.readouterr().err
    assert error == f"mcsplat: error: {tmp_path / 'empty.ply'}: holds no Gaussians (0 vertices), so there is nothing " \
        "to show\n"


@pytest.mark.filterwarnings("ignore:no training cameras shown")  # the scene is gone on purpose
def test_nan_gaussians_are_left_out_and_the_first_camera_looks_at_the_others(tiny_run, tmp_path, capsys):
    """A run whose scene is gone is looked at from around its Gaussians: the NaN or infinite ones are left out,
    saying how many (they would put that camera nowhere); a run of nothing else, or such a .ply, is one line."""
    pytest.importorskip("viser")
    import shutil

    from mcsplat.io.checkpoint import load_checkpoint, save_checkpoint
    from mcsplat.io.ply import read_ply, write_ply
    from mcsplat.viewer.saved import view_saved

    run = Path(shutil.copytree(tiny_run, tmp_path / "run"))
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "data": str(tmp_path / "gone")}))
    state = load_checkpoint(run / "checkpoint.pt")
    means = state["model"]["params.means"]
    total = means.shape[0]
    means[:5] = float("nan")
    state["model"]["params.log_scales"][9, 2] = float("inf")
    save_checkpoint(run / "checkpoint.pt", {k: v for k, v in state.items() if k != "version"})
    stop = threading.Event()
    stop.set()  # serve, then close at once
    with pytest.warns(UserWarning, match=rf"run: 6 of {total:,} Gaussians have NaN or infinite values: left out"):
        server = view_saved(run, "127.0.0.1", free_port(), torch.device("cpu"), stop, quiet=True)
    assert server.model.num_gaussians == total - 6
    wxyz, position, fov = server.initial_pose
    assert np.isfinite(np.concatenate([np.ravel(wxyz), np.ravel(position), [fov]])).all(), server.initial_pose

    means[:] = float("nan")
    save_checkpoint(run / "checkpoint.pt", {k: v for k, v in state.items() if k != "version"})
    params = read_ply(tiny_run / "point_cloud.ply")
    params["means"][:5] = float("nan")
    write_ply(tmp_path / "nan.ply", params)
    for path, expected in ((run, f"every one of its {total:,} Gaussians has NaN or infinite values, so there is "
                                 "nothing to show"), (tmp_path / "nan.ply", "NaN or infinite values in means")):
        capsys.readouterr()
        assert main(["view", str(path), "--port", str(free_port())]) == 2
        assert capsys.readouterr().err == f"mcsplat: error: {path}: {expected}\n"


def test_a_mesh_with_nan_vertices_is_shown_without_them(tmp_path):
    pytest.importorskip("viser")
    import trimesh

    from mcsplat.mesh import write_mesh
    from mcsplat.viewer.saved import serve_mesh

    ball = trimesh.creation.icosphere(subdivisions=2)
    ball.vertices[:3] = np.nan
    write_mesh(tmp_path / "ball.ply", ball)
    with pytest.warns(UserWarning, match=rf"ball.ply: 3 of {len(ball.vertices):,} vertices have NaN or infinite "
                                         "values: left out, with the faces they belong to"):
        server, _ = serve_mesh(tmp_path / "ball.ply", "127.0.0.1", free_port(), quiet=True)
    server.close()
    wxyz, position, fov = server.initial_pose
    assert np.isfinite(np.concatenate([np.ravel(wxyz), np.ravel(position), [fov]])).all(), server.initial_pose


def test_a_file_of_no_gaussians_is_one_line(tmp_path):
    """An empty .splat or a glTF whose accessors count 0 (any format's file of no Gaussians) says so, in one line,
    rather than a torch error."""
    from mcsplat.io.formats import write_gaussians
    from mcsplat.viewer.saved import load_for_viewing
    from tests.export.test_formats import random_gaussians

    (tmp_path / "empty.splat").write_bytes(b"")
    write_gaussians("gltf", tmp_path / "x.gltf", random_gaussians(8))
    document = json.loads((tmp_path / "x.gltf").read_text())
    for accessor in document["accessors"]:
        accessor.update(count=0)
    (tmp_path / "x.gltf").write_text(json.dumps(document))
    for path in (tmp_path / "empty.splat", tmp_path / "x.gltf"):
        with pytest.raises(MCSplatError, match=f"^{re.escape(str(path))}: holds no Gaussians"):
            load_for_viewing(path, torch.device("cpu"))
