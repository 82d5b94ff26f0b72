"""COLMAP scenes: `sparse/0/` (or `sparse/`) with cameras, images, points3D as .bin or .txt, and `images/`."""

from __future__ import annotations

import warnings
from pathlib import Path, PurePosixPath

import numpy as np

from . import colmap_files, images, undistort
from .assemble import Frame, Points, assemble
from .poses import check_translation, intrinsic_matrix, rigid_rotation, scale_intrinsics
from .scene import Background, Scene
from ..errors import DataError

MODEL_FILES = ("cameras", "images", "points3D")


def model_candidates(root: Path) -> list[Path]:
    return [root / "sparse" / "0", root / "sparse"]


def find_model(root: Path) -> tuple[Path, str] | None:
    """The folder and extension ("bin" or "txt") of a complete COLMAP model under root, or None."""
    for folder in model_candidates(root):
        for ext in ("bin", "txt"):
            if all((folder / f"{name}.{ext}").is_file() for name in MODEL_FILES):
                return folder, ext
    return None


def incomplete_model(root: Path) -> str | None:
    """A description of a COLMAP model folder that lacks some files, for the 'no scene found' message."""
    for folder in model_candidates(root):
        for ext in ("bin", "txt"):
            present = [name for name in MODEL_FILES if (folder / f"{name}.{ext}").is_file()]
            if present:
                missing = [f"{name}.{ext}" for name in MODEL_FILES if name not in present]
                return f"the COLMAP model in {folder} is incomplete ({', '.join(missing)} missing)"
    return None


def _read_reconstruction(folder: Path, ext: str):
    import pycolmap

    if ext == "bin":
        # pycolmap can hang or exhaust memory on a damaged .bin file: walk each one first.
        camera_ids = colmap_files.check_cameras_bin(folder / "cameras.bin")
        colmap_files.check_images_bin(folder / "images.bin", camera_ids)
        xyz, rgb = colmap_files.read_points3d_bin(folder / "points3D.bin")
    reconstruction = pycolmap.Reconstruction()
    try:
        if ext == "bin":
            reconstruction.read_binary(str(folder))
        else:
            reconstruction.read_text(str(folder))
    except Exception as exc:
        problem = colmap_files.diagnose_text_model(folder) if ext == "txt" else None
        if problem is None:
            reason = " ".join(str(exc).split())[:200]
            files = ", ".join(f"{name}.{ext}" for name in MODEL_FILES)
            problem = f"cannot read the COLMAP model in {folder} ({files}): {reason}"
        raise DataError(f"{problem}; the model is inconsistent or corrupt, export it again (colmap model_converter)") \
            from None
    if ext == "txt":
        ids = sorted(reconstruction.points3D.keys())
        xyz = np.array([reconstruction.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
        rgb = np.array([reconstruction.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    return reconstruction, xyz, rgb


def _intrinsics(camera, cameras_file: Path) -> np.ndarray:
    """K of a SIMPLE_PINHOLE or PINHOLE camera."""
    model = camera.model.name
    params = np.asarray(camera.params, dtype=np.float64)
    if model == "SIMPLE_PINHOLE":
        fx = fy = params[0]
        cx, cy = params[1:3]
    else:
        fx, fy, cx, cy = params[:4]
    if not np.isfinite(params).all() or fx <= 0 or fy <= 0:
        raise DataError(f"{cameras_file}: camera {camera.camera_id} has invalid parameters {params.tolist()}; "
                        "focal lengths must be positive numbers")
    return intrinsic_matrix(fx, fy, cx, cy)


def _fits(actual: tuple[int, int], camera_size: tuple[int, int], factor: int) -> bool:
    """Whether an image from an images_<factor>/ folder has the size of the camera shrunk by factor (+-1 px)."""
    if factor == 1:
        return actual == camera_size
    return all(abs(a - c / factor) <= 1.0 for a, c in zip(actual, camera_size))


def load_colmap(root: Path, downscale: int, background: Background | None, test_every: int) -> Scene:
    found = find_model(root)
    if found is None:
        raise DataError(incomplete_model(root) or f"no COLMAP model in {root}")
    folder, ext = found
    cameras_file, images_file = folder / f"cameras.{ext}", folder / f"images.{ext}"
    reconstruction, xyz, rgb = _read_reconstruction(folder, ext)

    # Distorted cameras are replaced by the pinhole camera their images are undistorted to (undistort.py).
    pinholes = {camera_id: undistort.pinhole_camera(camera, str(cameras_file))
                for camera_id, camera in reconstruction.cameras.items() if undistort.is_distorted(camera)}
    records = []  # (name, camera_id, K at camera size, camera size, world_to_camera)
    unposed = []
    for image in reconstruction.images.values():
        if not image.has_pose:
            unposed.append(image.name)
            continue
        camera = reconstruction.cameras[image.camera_id]
        K = _intrinsics(pinholes.get(image.camera_id, camera), cameras_file)
        where = f"{images_file}: image '{image.name}'"
        matrix = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        w2c = np.eye(4)
        w2c[:3, :3] = rigid_rotation(matrix[:3, :3], where)
        w2c[:3, 3] = check_translation(matrix[:3, 3], where)
        records.append((image.name, image.camera_id, K, (camera.width, camera.height), w2c))
    if unposed:
        warnings.warn(f"{images_file}: skipping {len(unposed)} images without a pose: {', '.join(unposed[:5])}"
                      + (" ..." if len(unposed) > 5 else ""), stacklevel=3)
    if not records:
        raise DataError(f"{images_file} holds no registered images; run COLMAP's mapper until images are registered")
    records.sort(key=lambda r: r[0])

    image_dir, factor = images.choose_image_dir(root, downscale)
    paths = [image_dir / name for name, *_ in records]
    for path, (name, *_rest) in zip(paths, records):
        if not path.is_file():
            raise DataError(f"image '{name}' listed in {images_file} is missing: {path} does not exist")
    sizes = images.probe_sizes(paths)

    size_of_camera: dict[int, tuple[tuple[int, int], Path]] = {}
    frames = []
    for path, size, (name, camera_id, K, camera_size, w2c) in zip(paths, sizes, records):
        if not _fits(size, camera_size, factor):
            expected = f"{camera_size[0]}x{camera_size[1]}" + (f" / {factor}" if factor > 1 else "")
            raise DataError(f"image {path} is {size[0]}x{size[1]} but its camera {camera_id} in {cameras_file} is "
                            f"{expected}; use the images the model was made from (or undistorted with it)")
        first = size_of_camera.setdefault(camera_id, (size, path))
        if first[0] != size:
            raise DataError(f"image {path} is {size[0]}x{size[1]} but {first[1]} of the same camera {camera_id} is "
                            f"{first[0][0]}x{first[0][1]}; all images of one camera must have the same size")
        view_name = str(PurePosixPath(name).with_suffix(""))
        if camera_id in pinholes:
            # Undistort at the file's size (an images_N/ copy has the camera shrunk by N), then resize like the rest.
            distorted = undistort.rescaled_camera(reconstruction.cameras[camera_id], size)
            pinhole = undistort.pinhole_camera(distorted, str(cameras_file)) if factor > 1 else pinholes[camera_id]
            undistorted_size = (pinhole.width, pinhole.height)
            K = _intrinsics(pinhole, cameras_file)
            target = images.downscaled_size(*undistorted_size, downscale / factor) if downscale > factor \
                else undistorted_size
            frames.append(Frame(path, view_name, scale_intrinsics(K, undistorted_size, target), w2c, target,
                                undistort.Job(path, distorted, pinhole, target)))
            continue
        target = images.downscaled_size(*camera_size, downscale) if downscale > factor else size
        frames.append(Frame(path, view_name, scale_intrinsics(K, camera_size, target), w2c, target))

    resized = downscale > factor
    note = f"images from {image_dir.name}/" + (f", resized to 1/{downscale} of the camera size" if resized else "")
    if downscale < factor:
        note += f" (no folder for downscale {downscale}; using the smaller images as they are)"
    return assemble(frames, kind="colmap", root=root, background=background, test_every=test_every,
                    points=Points(xyz, rgb, str(folder / f"points3D.{ext}")),
                    notes=[f"model: {folder.relative_to(root)}/*.{ext}", note])

