"""`mcsplat view`: the viewer on a finished (or stopped) run, on any 3DGS .ply, on a file of Gaussians that
`mcsplat export` writes (.splat, .compressed.ply, .spz, .sog, glTF's KHR_gaussian_splatting), or on a mesh (.ply with
faces, .glb, .obj), which the browser draws itself (viser's mesh)."""

from __future__ import annotations

import threading
import warnings
from pathlib import Path
from typing import Sequence

import torch

from ..run import trained as trained_run
from ..errors import MCSplatError
from ..gaussians import GaussianModel
from ..io.formats import format_named_by, read_gaussians
from ..io.formats.gltf import holds_gaussians
from ..io.ply import read_ply
from ..mesh import holds_mesh, read_mesh
from .access import check_listen_address
from .server import ViewerServer


def load_for_viewing(path: Path, device: torch.device):
    """(model, training cameras, background, scene radius) of a run directory or a file of Gaussians."""
    if path.is_dir():
        run = trained_run.load(path, device)
        model = finite_gaussians(run.model, path)
        try:
            scene = run.scene
        except MCSplatError as error:
            warnings.warn(f"no training cameras shown: the scene cannot be loaded ({error})")
            return model, [], (0.0, 0.0, 0.0), _radius_of(model)
        return model, [v.camera for v in scene.train], run.background, scene.radius
    named = format_named_by(path)  # the formats `mcsplat export` writes; a .glb / .gltf may be a mesh's instead
    if named not in (None, "ply", "glb", "gltf") or (named in ("glb", "gltf") and holds_gaussians(path)):
        params = read_gaussians(named, path)
        model = finite_gaussians(GaussianModel(**{k: _tensor(v) for k, v in params.items()}), path)
        return model.to(device), [], (0.0, 0.0, 0.0), _radius_of(model)
    if path.suffix.lower() != ".ply":
        raise MCSplatError(f"{path}: give a run directory, a 3DGS .ply file, a file of Gaussians (.splat, "
                           ".compressed.ply, .spz, .sog, .glb, .gltf) or a mesh (.ply, .glb, .obj)")
    model = GaussianModel(**read_ply(path)).to(device)
    if model.num_gaussians == 0:
        raise MCSplatError(f"{path}: holds no Gaussians (0 vertices), so there is nothing to show")
    return model, [], (0.0, 0.0, 0.0), _radius_of(model)  # read_ply refuses NaN or infinite values


def _tensor(values) -> torch.Tensor:
    """A reader's array as a tensor; an empty one (the SH rest of degree 0) made afresh, since numpy gives it strides
    of 0 that the render kernels refuse."""
    return torch.from_numpy(values) if values.size else torch.zeros(values.shape, dtype=torch.float32)


def finite_gaussians(model: GaussianModel, source: Path) -> GaussianModel:
    """`model` without the Gaussians that have a NaN or infinite parameter (saying how many), which would render
    nothing useful and put the first camera nowhere; a one-line error when none is left."""
    if model.num_gaussians == 0:  # a file of any format may hold none (an empty .splat, glTF accessors of count 0)
        raise MCSplatError(f"{source}: holds no Gaussians, so there is nothing to show")
    finite = torch.ones(model.num_gaussians, dtype=torch.bool, device=model.means.device)
    for value in model.params.values():
        finite &= torch.isfinite(value.detach()).reshape(model.num_gaussians, -1).all(dim=1)
    dropped = model.num_gaussians - int(finite.sum())
    if dropped == 0:
        return model
    if dropped == model.num_gaussians:
        raise MCSplatError(f"{source}: every one of its {dropped:,} Gaussians has NaN or infinite values, so there is "
                           f"nothing to show")
    warnings.warn(f"{source}: {dropped:,} of {model.num_gaussians:,} Gaussians have NaN or infinite values: left out")
    return model.subset(finite)


def _radius_of(model) -> float:
    means = model.means.detach()
    return float((means - means.median(dim=0).values).norm(dim=1).quantile(0.9)) if means.shape[0] else 1.0


def initial_pose_for(centre, radius: float):
    """A view from outside the scene towards `centre` [3], for a file without cameras (OpenCV axes: y down)."""
    import numpy as np

    from .cameras import matrix_to_quat

    centre = np.asarray(centre, dtype=np.float64)
    position = centre + np.array([0.0, -1.0, -2.5]) * radius
    forward = (centre - position) / np.linalg.norm(centre - position)
    right = np.cross(forward, [0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return matrix_to_quat(np.stack([right, down, forward], axis=1)), position, np.deg2rad(50.0)


def view_saved(path: Path, host: str, port: int, device: torch.device, stop: threading.Event | None = None,
               quiet: bool = False, origins: Sequence[str] = ()) -> ViewerServer:
    """Serve the viewer until `stop` is set (Ctrl-C from the CLI); returns the stopped server."""
    check_listen_address(host, port)  # before the model is loaded
    if Path(path).is_file() and holds_mesh(Path(path)):
        return view_mesh(Path(path), host, port, stop, quiet, origins)
    model, cameras, background, radius = load_for_viewing(Path(path), device)
    with torch.no_grad():
        model.requires_grad_(False)
    server = ViewerServer(host, port, lock=threading.RLock(), scene_radius=radius, background=background,
                          max_sh_degree=model.sh_degree, training=False, quiet=quiet, origins=origins)
    try:
        if cameras:
            server.add_cameras(cameras)
        else:
            server.initial_pose = initial_pose_for(model.means.detach().median(dim=0).values.cpu(), radius)
        server.set_model(model)
        server.set_stats(f"{Path(path).name}: {model.num_gaussians:,} Gaussians, SH degree {model.sh_degree}")
        (stop or threading.Event()).wait()
    finally:
        server.close()
    return server


def view_mesh(path: Path, host: str, port: int, stop: threading.Event | None = None, quiet: bool = False,
              origins: Sequence[str] = ()) -> ViewerServer:
    """Serve a mesh file until `stop` is set; returns the stopped server."""
    server, _ = serve_mesh(path, host, port, quiet, origins)
    try:
        (stop or threading.Event()).wait()
    finally:
        server.close()
    return server


def serve_mesh(path: Path, host: str, port: int, quiet: bool = False, origins: Sequence[str] = ()):
    """(server, viser's handle of the mesh): the browser draws the mesh itself, vertex colours kept; nothing is
    rendered here, so the controls of the splats' renders are hidden."""
    import numpy as np

    mesh = finite_vertices(read_mesh(path), path)
    low, high = mesh.bounds
    radius = float(np.linalg.norm(high - low)) / 2 or 1.0
    server = ViewerServer(host, port, lock=threading.RLock(), scene_radius=radius, background=(1.0, 1.0, 1.0),
                          max_sh_degree=0, training=False, quiet=quiet, origins=origins)
    try:
        for control in (server.mode, server.sh_degree, server.show_cameras):
            control.visible = False
        handle = server.server.scene.add_mesh_trimesh("/mesh", mesh)
        server.initial_pose = initial_pose_for((low + high) / 2, radius)
        server.set_stats(f"{path.name}: {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces")
    except BaseException:
        server.close()
        raise
    return server, handle


def finite_vertices(mesh, source: Path):
    """`mesh` without its NaN or infinite vertices and the faces they belong to (saying how many), which would put
    the first camera nowhere; a one-line error when no face is left."""
    import numpy as np

    finite = np.isfinite(mesh.vertices).all(axis=1)
    dropped = int((~finite).sum())
    if dropped == 0:
        return mesh
    faces = finite[mesh.faces].all(axis=1)
    if not faces.any():
        raise MCSplatError(f"{source}: every face has a vertex with NaN or infinite values, so there is nothing to "
                           f"show")
    warnings.warn(f"{source}: {dropped:,} of {len(mesh.vertices):,} vertices have NaN or infinite values: left out, "
                  f"with the faces they belong to")
    kept = mesh.submesh([np.flatnonzero(faces)], append=True, repair=False)
    kept.remove_unreferenced_vertices()
    return kept
