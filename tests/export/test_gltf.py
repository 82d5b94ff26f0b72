"""glTF export (KHR_gaussian_splatting, .glb and .gltf + .bin): the container's bytes, our reader's round trip, the
Khronos glTF validator's report, what three.js's own loader of the extension decodes from the files against the model,
three.js's picture of the .glb against mcsplat's render; `mcsplat export --format glb|gltf` of a trained run.

The external readers are npm packages run with Node (tests/support/node/): they are looked for in NODE_PATH's folders
and npm's global folder (.ci/run installs them there on CI); the tests that need them (or headless Chromium) skip,
with the reason, without."""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mcsplat.cli import main
from mcsplat.io.formats import read_gaussians, write_gaussians
from mcsplat.io.ply import read_ply

from tests.export.test_formats import random_gaussians, sigmoid

C0 = 0.28209479177387814
NODE_SCRIPTS = Path(__file__).parents[1] / "support" / "node"
THREE, VALIDATOR = "three", "gltf-validator"
PINNED = {THREE: "three@0.187.0", VALIDATOR: "gltf-validator@2.0.0-dev.3.10"}  # what .ci/run installs
FLIP = np.diag([1.0, -1.0, -1.0])  # the 3DGS frame turned 180 degrees about x into glTF's +Y up
SH_FLIP = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=np.float64)  # odd in y and z


def node_modules_with(package: str) -> Path | None:
    """The node_modules folder that holds `package`: one of NODE_PATH's, else npm's global one."""
    if shutil.which("node") is None:
        return None
    folders = [Path(p) for p in os.environ.get("NODE_PATH", "").split(os.pathsep) if p]
    if shutil.which("npm"):
        root = subprocess.run(["npm", "root", "-g"], capture_output=True, text=True, timeout=60).stdout.strip()
        folders.append(Path(root))
    return next((folder for folder in folders if (folder / package / "package.json").is_file()), None)


def run_node(package: str, script: str, file: Path) -> dict:
    modules = node_modules_with(package)
    if modules is None:
        pytest.skip(f"no Node with the npm package {package}: npm install -g {PINNED[package]} or set NODE_PATH "
                    "(.ci/run installs it on CI)")
    done = subprocess.run(["node", str(NODE_SCRIPTS / script), str(modules), str(file)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def rotation_matrices(quats_wxyz: np.ndarray) -> np.ndarray:
    q = quats_wxyz.astype(np.float64) / np.linalg.norm(quats_wxyz.astype(np.float64), axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def test_glb_container_and_attributes_follow_the_specifications(tmp_path):
    g = random_gaussians(40, degree=2)
    write_gaussians("glb", tmp_path / "x.glb", g)
    data = (tmp_path / "x.glb").read_bytes()
    magic, version, length = struct.unpack_from("<III", data)
    json_length, json_kind = struct.unpack_from("<II", data, 12)
    bin_length, bin_kind = struct.unpack_from("<II", data, 20 + json_length)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    assert (json_kind, bin_kind) == (0x4E4F534A, 0x004E4942) and json_length % 4 == 0 and bin_length % 4 == 0
    document = json.loads(data[20:20 + json_length])
    primitive = document["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0 and primitive["extensions"]["KHR_gaussian_splatting"]["kernel"] == "ellipse"
    names = [f"KHR_gaussian_splatting:SH_DEGREE_{d}_COEF_{m}" for d in range(3) for m in range(2 * d + 1)]
    assert set(primitive["attributes"]) == {"POSITION", "KHR_gaussian_splatting:ROTATION",
                                            "KHR_gaussian_splatting:SCALE", "KHR_gaussian_splatting:OPACITY", *names}
    assert document["extensionsUsed"] == ["KHR_gaussian_splatting"] and "extensionsRequired" not in document
    binary = data[28 + json_length:28 + json_length + bin_length]

    def attribute(semantic):
        accessor = document["accessors"][primitive["attributes"][semantic]]
        view = document["bufferViews"][accessor["bufferView"]]
        return np.frombuffer(binary, "<f4", view["byteLength"] // 4, view["byteOffset"]).reshape(accessor["count"], -1)

    # Linear scales, alpha, x y z w quaternions, all in the y-up frame; the SH of degree 2 coefficient 0 (index 3
    # of the 3DGS rest coefficients, basis xy) changes sign under y -> -y.
    assert np.allclose(attribute("POSITION"), g["means"] @ FLIP)
    assert np.allclose(attribute("KHR_gaussian_splatting:SCALE"), np.exp(g["log_scales"]), rtol=1e-6)
    assert np.allclose(attribute("KHR_gaussian_splatting:OPACITY")[:, 0], sigmoid(g["opacity_logits"]), rtol=1e-6)
    unit = g["quats"] / np.linalg.norm(g["quats"], axis=1, keepdims=True)
    assert np.allclose(attribute("KHR_gaussian_splatting:ROTATION"), unit[:, [1, 2, 3, 0]] * [1, -1, -1, 1], atol=1e-6)
    assert np.array_equal(attribute("KHR_gaussian_splatting:SH_DEGREE_0_COEF_0"), g["sh0"][:, 0])
    assert np.array_equal(attribute("KHR_gaussian_splatting:SH_DEGREE_2_COEF_0"), -g["shN"][:, 3])
    assert document["accessors"][primitive["attributes"]["POSITION"]]["min"] == pytest.approx(
        (g["means"] @ FLIP).min(axis=0))


@pytest.mark.parametrize("name", ["glb", "gltf"])
@pytest.mark.parametrize("degree", [0, 3])
def test_read_back_is_the_model(tmp_path, name, degree):
    g = random_gaussians(64, degree=degree, seed=degree)
    write_gaussians(name, tmp_path / f"x.{name}", g)
    back = read_gaussians(name, tmp_path / f"x.{name}")
    assert (tmp_path / "x.bin").is_file() == (name == "gltf")
    for key in ("means", "sh0", "shN"):
        assert np.array_equal(back[key], g[key]), key
    assert np.allclose(back["log_scales"], g["log_scales"], atol=1e-6)
    assert np.allclose(sigmoid(back["opacity_logits"]), sigmoid(g["opacity_logits"]), atol=1e-6)
    assert np.allclose(rotation_matrices(back["quats"]), rotation_matrices(g["quats"]), atol=1e-6)


def test_a_damaged_gltf_is_one_line_naming_it(tmp_path, capsys):
    """`view` reads any .glb / .gltf a user hands it: cut short, an accessor past its buffer, a missing attribute or
    attributes of different counts are one line naming the file, never a traceback."""
    from mcsplat.errors import MCSplatError

    write_gaussians("glb", tmp_path / "good.glb", random_gaussians(64, degree=1, seed=4))
    whole = (tmp_path / "good.glb").read_bytes()
    (tmp_path / "cut.glb").write_bytes(whole[:len(whole) // 2])
    write_gaussians("gltf", tmp_path / "x.gltf", random_gaussians(64, degree=1, seed=4))
    document = json.loads((tmp_path / "x.gltf").read_text())
    damaged = {}
    for name, change in (("past_the_end", lambda d: d["accessors"][0].update(count=10**6)),
                         ("no_scale", lambda d: d["meshes"][0]["primitives"][0]["attributes"].pop(
                             "KHR_gaussian_splatting:SCALE")),
                         ("counts_differ", lambda d: d["accessors"][0].update(count=32))):
        edited = json.loads(json.dumps(document))
        change(edited)
        (tmp_path / f"{name}.gltf").write_text(json.dumps(edited))
        damaged[name] = tmp_path / f"{name}.gltf"
    for path in (tmp_path / "cut.glb", *damaged.values()):
        with pytest.raises(MCSplatError, match=f"^{path}: ") as error:
            read_gaussians(path.suffix[1:], path)
        assert "\n" not in str(error.value)
    assert main(["view", str(damaged["past_the_end"])]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("name", ["glb", "gltf"])
def test_khronos_validator_finds_nothing_but_the_extension_it_predates(tmp_path, name):
    """gltf-validator 2.0.0-dev.3.10 (the newest on npm) predates KHR_gaussian_splatting: it reports the extension
    as one it cannot check and each of its attribute semantics as an invalid name. Nothing else may be reported."""
    g = random_gaussians(30, degree=3)
    path = tmp_path / f"x.{name}"
    write_gaussians(name, path, g)
    issues = run_node(VALIDATOR, "gltf_validate.mjs", path)
    messages = [(m["code"], m["pointer"]) for m in issues["messages"]]
    predating = [m for m in messages if m[0] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE"
                 and m[1].startswith("/meshes/0/primitives/0/attributes/KHR_gaussian_splatting:")]
    assert len(predating) == 3 + 1 + 15 and issues["numErrors"] == len(predating), messages
    assert [m for m in messages if m not in predating] == [("UNSUPPORTED_EXTENSION", "/extensionsUsed/0")], messages
    assert issues["numWarnings"] == 0 and issues["numHints"] == 0
    if name == "gltf":  # the validator reads the .bin: without it, one more error
        (tmp_path / "x.bin").unlink()
        assert run_node(VALIDATOR, "gltf_validate.mjs", path)["numErrors"] == len(predating) + 1


@pytest.mark.parametrize("name", ["glb", "gltf"])
def test_three_js_loader_decodes_the_model(tmp_path, name):
    """three.js's GLTFGaussianSplatLoaderExtension (its reading of the specification, nobody's here) turns the file
    into centres, covariances, colour bytes and SH bytes: each is the model's, turned into glTF's frame."""
    g = random_gaussians(50, degree=3, seed=7)
    path = tmp_path / f"x.{name}"
    write_gaussians(name, path, g)
    decoded = run_node(THREE, "three_gltf_splats.mjs", path)
    assert decoded["extension"]["KHR_gaussian_splatting"]["colorSpace"] == "srgb_rec709_display"

    def values(attribute):
        return np.array(decoded[attribute]["values"], dtype=np.float64)

    assert decoded["position"]["count"] == 50
    assert np.allclose(values("position").reshape(-1, 3), g["means"] @ FLIP, atol=1e-6)
    rotations = rotation_matrices(g["quats"])
    covariance = FLIP @ rotations @ (np.exp(2.0 * g["log_scales"].astype(np.float64))[:, :, None] *
                                     rotations.transpose(0, 2, 1)) @ FLIP
    upper = covariance[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    assert np.allclose(values("covariance").reshape(-1, 6), upper, rtol=1e-4, atol=1e-9)
    rgba = values("color").reshape(-1, 4)
    colour = np.clip(0.5 + C0 * g["sh0"][:, 0].astype(np.float64), 0, 1) * 255
    assert np.abs(rgba[:, :3] - colour).max() <= 0.51
    assert np.abs(rgba[:, 3] - sigmoid(g["opacity_logits"]) * 255).max() <= 0.51
    rest = g["shN"].astype(np.float64) * SH_FLIP[:, None]
    first = 0
    for degree, words in ((1, 3), (2, 4), (3, 6)):
        count = 2 * degree + 1
        band = values(f"sphericalHarmonics{degree}").reshape(50, words * 4)[:, :count * 3].reshape(50, count, 3)
        assert np.abs(band - (rest[:, first:first + count] * 128 + 128)).max() <= 0.51, degree
        first += count


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_three_js_draws_the_glb_as_mcsplat_renders_it(tiny_run, tmp_path):
    """three.js's WebGPURenderer (WebGL 2 backend, headless Chromium) draws the exported .glb from a test camera of
    the run, turned into glTF's frame; mcsplat renders the model from the same camera. The pictures differ by what
    the two rasterisers do differently (three.js keeps SH as bytes, its own kernel cut-off and sort), not by where
    or what colour the Gaussians are: a mirrored picture is far further."""
    import functools
    import http.server
    import threading

    import torch
    from PIL import Image

    from mcsplat.run import trained as trained_run
    from mcsplat.render import render

    pytest.importorskip("websockets", reason="the browser tests' websockets (a dependency of viser) is not installed")
    from tests.support.browser import Browser, find_browser

    if find_browser() is None:
        pytest.skip("no headless Chromium: apt-get install chromium-headless-shell (.ci/run does so on CI)")
    modules = node_modules_with(THREE)
    if modules is None:
        pytest.skip(f"no Node with the npm package {THREE}: npm install -g {PINNED[THREE]} or set NODE_PATH "
                    "(.ci/run installs it on CI)")
    folder = tmp_path / "page"
    folder.mkdir()
    (folder / "three").symlink_to(modules / THREE)
    shutil.copy(NODE_SCRIPTS / "three_splat_page.html", folder / "page.html")
    assert main(["export", str(tiny_run), "--out", str(folder / "scene.glb")]) == 0

    run = trained_run.load(tiny_run, torch.device("cpu"))
    camera = run.scene.test[0].camera
    width, height = camera.width, camera.height
    assert camera.K[0, 2] == width / 2 and camera.K[1, 2] == height / 2, "the page's projection is centred"
    with torch.no_grad():
        ours = render(run.model, camera, background=[0.0, 0.0, 0.0]).rgb.clamp(0, 1).numpy().astype(np.float64)
    # three.js's camera looks down -z with y up: OpenCV's camera axes with y and z turned, in glTF's world frame.
    turn = np.diag([1.0, -1.0, -1.0, 1.0])
    camera_to_world = turn @ np.linalg.inv(camera.world_to_camera.double().numpy()) @ turn
    view = {"width": width, "height": height, "file": "scene.glb", "cameraToWorld": camera_to_world.T.ravel().tolist(),
            "fovy": float(np.degrees(2 * np.arctan(height / (2 * float(camera.K[1, 1])))))}

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    browser = Browser(width=width, height=height)
    try:
        browser.call("Page.navigate", url=f"http://127.0.0.1:{server.server_address[1]}/page.html")
        browser.wait_for("window.ready === true")
        assert browser.evaluate(f"window.draw({json.dumps(view)})", timeout=120) == "drawn"
        browser.screenshot(tmp_path / "three.png")
    finally:
        browser.close()
        server.shutdown()
    theirs = np.asarray(Image.open(tmp_path / "three.png").convert("RGB"), dtype=np.float64) / 255.0
    assert theirs.shape == ours.shape
    same, mirrored = psnr(theirs, ours), psnr(theirs, ours[:, ::-1])
    assert same > 26.0 and same > mirrored + 8.0, (same, mirrored)


def test_cli_exports_glb_and_gltf_of_a_trained_run(tiny_run, tmp_path, capsys):
    total = read_ply(tiny_run / "point_cloud.ply")["means"].shape[0]
    assert main(["export", str(tiny_run), "--format", "glb"]) == 0
    assert "point_cloud.glb" in capsys.readouterr().out
    assert read_gaussians("glb", tiny_run / "point_cloud.glb")["means"].shape[0] == total
    assert main(["export", str(tiny_run), "--out", str(tmp_path / "scene.gltf"), "--max-gaussians", "300"]) == 0
    line = capsys.readouterr().out
    assert f"{tmp_path / 'scene.gltf'} and {tmp_path / 'scene.bin'}" in line and "300 of" in line
    assert read_gaussians("gltf", tmp_path / "scene.gltf")["means"].shape[0] == 300
    # 59 float32 each (3 + 4 + 3 + 1 + 16 x 3), unquantised, and a few kB of JSON: 3 floats each less than the .ply
    overhead = (tiny_run / "point_cloud.glb").stat().st_size - 59 * 4 * total
    assert 1000 < overhead < 8000, overhead


def test_view_opens_a_glb_of_gaussians_as_gaussians_and_a_mesh_glb_as_a_mesh(tmp_path):
    """`mcsplat view` tells the two kinds of .glb apart by the extension the file names."""
    pytest.importorskip("viser", reason="the viewer's optional dependency viser is not installed")
    import torch
    import trimesh

    from mcsplat.mesh import holds_mesh
    from mcsplat.viewer.saved import load_for_viewing

    g = random_gaussians(20, degree=1)
    for name in ("glb", "gltf"):
        write_gaussians(name, tmp_path / f"x.{name}", g)
        assert not holds_mesh(tmp_path / f"x.{name}")
        model, cameras, _, _ = load_for_viewing(tmp_path / f"x.{name}", torch.device("cpu"))
        assert cameras == [] and torch.equal(model.means.detach(), torch.from_numpy(g["means"]))
        assert model.sh_degree == 1
    trimesh.creation.box().export(tmp_path / "box.glb")
    assert holds_mesh(tmp_path / "box.glb")


def malformed_documents(document: dict) -> dict[str, object]:
    """Ways a .gltf handed to `view` may be wrong, each the good `document` changed in one place."""
    def changed(change) -> dict:
        edited = json.loads(json.dumps(document))
        change(edited)
        return edited

    def primitive(d: dict) -> dict:
        return d["meshes"][0]["primitives"][0]

    def accessor(d: dict) -> dict:
        return d["accessors"][primitive(d)["attributes"]["POSITION"]]

    def set_primitive(d: dict, value) -> None:
        d["meshes"][0]["primitives"][0] = value

    return {
        "buffer_without_uri": changed(lambda d: d["buffers"][0].pop("uri")),
        "uri_up": changed(lambda d: d["buffers"][0].update(uri="..")),
        "uri_here": changed(lambda d: d["buffers"][0].update(uri=".")),
        "uri_a_folder": changed(lambda d: d["buffers"][0].update(uri="sub")),
        "uri_not_text": changed(lambda d: d["buffers"][0].update(uri=5)),
        "uri_absolute": changed(lambda d: d["buffers"][0].update(uri="/etc/hostname")),
        "uri_data": changed(lambda d: d["buffers"][0].update(uri="data:application/octet-stream;base64,AAAA")),
        "buffer_longer_than_its_file": changed(lambda d: d["buffers"][0].update(
            byteLength=d["buffers"][0]["byteLength"] + 64)),
        "buffer_not_an_object": changed(lambda d: d.update(buffers=[3])),
        "primitive_not_an_object": changed(lambda d: set_primitive(d, 5)),
        "primitive_a_list": changed(lambda d: set_primitive(d, [])),
        "mesh_not_an_object": changed(lambda d: d.update(meshes=[7])),
        "extensions_a_list": changed(lambda d: primitive(d).update(extensions=["KHR_gaussian_splatting"])),
        "attributes_a_list": changed(lambda d: primitive(d).update(attributes=[0, 1])),
        "accessor_index_negative": changed(lambda d: primitive(d)["attributes"].update(POSITION=-1)),
        "accessor_index_true": changed(lambda d: primitive(d)["attributes"].update(POSITION=True)),
        "accessor_index_past_the_list": changed(lambda d: primitive(d)["attributes"].update(POSITION=999)),
        "accessor_not_an_object": changed(lambda d: d["accessors"].__setitem__(0, 3)),
        "count_text": changed(lambda d: accessor(d).update(count="64")),
        "count_negative": changed(lambda d: accessor(d).update(count=-1)),
        "count_beyond_any_file": changed(lambda d: accessor(d).update(count=10**30)),
        "type_of_another_width": changed(lambda d: accessor(d).update(type="SCALAR")),
        "type_unknown": changed(lambda d: accessor(d).update(type="MAT4")),
        "offset_unaligned": changed(lambda d: accessor(d).update(byteOffset=1)),
        "offset_negative": changed(lambda d: accessor(d).update(byteOffset=-4)),
        "offset_text": changed(lambda d: accessor(d).update(byteOffset="4")),
        "past_its_buffer_view": changed(lambda d: d["bufferViews"][accessor(d)["bufferView"]].update(byteLength=4)),
        "view_of_another_buffer": changed(lambda d: d["bufferViews"][accessor(d)["bufferView"]].update(buffer=1)),
        "view_interleaved": changed(lambda d: d["bufferViews"][accessor(d)["bufferView"]].update(byteStride=16)),
        "view_not_an_object": changed(lambda d: d["bufferViews"].__setitem__(accessor(d)["bufferView"], None)),
        "view_past_the_buffer": changed(lambda d: d["bufferViews"][accessor(d)["bufferView"]].update(
            byteOffset=d["buffers"][0]["byteLength"])),
        "document_not_an_object": [document],
    }


def glb_of(document: object, binary: bytes) -> bytes:
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if binary:
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)) + chunks


def as_in_a_glb(document: object) -> object:
    """The document as a .glb's: its buffer is the BIN chunk, which no uri names."""
    buffers = document.get("buffers") if isinstance(document, dict) else None
    if buffers and isinstance(buffers[0], dict):
        buffers[0].pop("uri", None)
    return document


def test_every_malformation_of_a_gltf_is_one_line_naming_it(tmp_path):
    """A buffer's uri is a file name beside the .gltf and nothing else; a part of the wrong type, an index out of
    its list, a count or offset that reads outside its buffer view or buffer: one line naming the file, never a
    traceback nor Gaussians read from the wrong bytes."""
    import re

    from mcsplat.errors import MCSplatError
    from mcsplat.io.formats.gltf import holds_gaussians

    write_gaussians("gltf", tmp_path / "x.gltf", random_gaussians(64, degree=1, seed=4))
    (tmp_path / "sub").mkdir()
    document, binary = json.loads((tmp_path / "x.gltf").read_text()), (tmp_path / "x.bin").read_bytes()
    files = []
    for name, edited in malformed_documents(document).items():
        (tmp_path / f"{name}.gltf").write_text(json.dumps(edited))
        files.append(tmp_path / f"{name}.gltf")
        if not name.startswith(("uri_", "buffer_without_uri")):  # a .glb's buffer is its own BIN chunk
            (tmp_path / f"{name}.glb").write_bytes(glb_of(as_in_a_glb(edited), binary))
            files.append(tmp_path / f"{name}.glb")
    with_uri = json.loads(json.dumps(document))
    (tmp_path / "buffer_with_uri.glb").write_bytes(glb_of(with_uri, binary))
    no_chunk = json.loads(json.dumps(document))
    no_chunk["buffers"][0].pop("uri")
    (tmp_path / "without_its_bin_chunk.glb").write_bytes(glb_of(no_chunk, b""))
    files += [tmp_path / "buffer_with_uri.glb", tmp_path / "without_its_bin_chunk.glb"]
    for path in files:
        holds_gaussians(path)  # never raises: the viewer asks it of any .glb / .gltf
        with pytest.raises(MCSplatError, match=f"^{re.escape(str(path))}: ") as error:
            read_gaussians(path.suffix[1:], path)
        assert "\n" not in str(error.value), path
    assert not holds_gaussians(tmp_path / "document_not_an_object.gltf")


@pytest.mark.parametrize("name", ["buffer_without_uri", "uri_up", "primitive_not_an_object"])
def test_view_of_a_malformed_gltf_is_one_line(tmp_path, capsys, name):
    """The issue's cases, through the command."""
    write_gaussians("gltf", tmp_path / "x.gltf", random_gaussians(16, seed=5))
    edited = malformed_documents(json.loads((tmp_path / "x.gltf").read_text()))[name]
    (tmp_path / f"{name}.gltf").write_text(json.dumps(edited))
    capsys.readouterr()
    assert main(["view", str(tmp_path / f"{name}.gltf")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("mcsplat: error:") and error.count("\n") == 1 and f"{name}.gltf" in error, error
