"""Structure from motion with pycolmap (no COLMAP binary): SIFT features, matching, incremental mapping."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal


Matcher = Literal["auto", "exhaustive", "sequential"]
MIN_REGISTERED = 3  # images a model needs to be a scene
EXTRACT_CHUNK = 16  # images per extract_features call: the progress bar moves between calls


@dataclass
class SfmOptions:
    matcher: Matcher = "auto"
    camera_model: str = "SIMPLE_RADIAL"
    max_size: int = 1600
    overlap: int = 15
    threads: int | None = None
    use_gpu: bool = True  # used only where pycolmap was built with CUDA
    mask_path: str | None = None  # COLMAP's masks (<image name>.png, 0: no features there)


@dataclass
class SfmResult:
    reconstruction: object  # pycolmap.Reconstruction: the model with the most registered images (None: no model)
    models: int
    matcher: str
    seconds: dict[str, float] = field(default_factory=dict)
    model_images: list[set[str]] = field(default_factory=list)  # the names registered in each model, the kept first


def choose_matcher(matcher: Matcher, from_video: bool, count: int) -> str:
    """Sequential for video frames (neighbours in time overlap), exhaustive for photos in no particular order."""
    if matcher != "auto":
        return matcher
    return "sequential" if from_video else "exhaustive"


def by_size(names: list[str], sizes: list[tuple[int, int]]) -> list[list[str]]:
    """The images of each size (width, height), the most common size first."""
    groups: dict[tuple[int, int], list[str]] = {}
    for name, size in zip(names, sizes):
        groups.setdefault(tuple(size), []).append(name)
    return [names for _, names in sorted(groups.items(), key=lambda item: -len(item[1]))]


def extract_features(database: Path, image_dir: Path, groups: list[list[str]], *, camera_model: str,
                     per_image: bool, max_size: int, threads: int, gpu: bool, progress: bool = True,
                     max_features: int | None = None, mask_path: str | None = None) -> float:
    """SIFT features into `database`: the images of each group share one camera (a phone's or a video's, for one
    image size), or each image has its own (`per_image`). Images go in chunks so that a progress bar moves and
    Ctrl-C is heard between them; at most `max_features` per image (COLMAP's 8,192 by default). Returns the seconds
    it took."""
    import pycolmap
    from tqdm import tqdm

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if mask_path is not None:
        reader.mask_path = mask_path
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.max_image_size = max_size
    extraction.use_gpu = gpu
    if max_features is not None:
        extraction.sift.max_num_features = max_features
    mode = pycolmap.CameraMode.PER_IMAGE if per_image else pycolmap.CameraMode.SINGLE
    device = pycolmap.Device.cuda if gpu else pycolmap.Device.cpu
    start = time.perf_counter()
    with tqdm(total=sum(map(len, groups)), desc="features", unit="image", disable=not progress, leave=False) as bar:
        for group in groups:
            reader.existing_camera_id = -1  # the group's first chunk makes its camera
            for first in range(0, len(group), EXTRACT_CHUNK):
                chunk = group[first:first + EXTRACT_CHUNK]
                pycolmap.extract_features(database, image_dir, image_names=chunk, camera_mode=mode,
                                          reader_options=reader, extraction_options=extraction, device=device)
                if not per_image and reader.existing_camera_id == -1:  # later chunks join it
                    reader.existing_camera_id = _camera_of(database, chunk[0])
                bar.update(len(chunk))
    return time.perf_counter() - start


def match_features(database: Path, matcher: str, *, overlap: int, threads: int, gpu: bool,
                   progress: bool = True) -> float:
    """Match every pair (exhaustive) or each image with its `overlap` neighbours in name order (sequential).
    Returns the seconds it took."""
    import pycolmap
    from tqdm import tqdm

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = gpu
    device = pycolmap.Device.cuda if gpu else pycolmap.Device.cpu
    start = time.perf_counter()
    with tqdm(total=1, desc=f"matching ({matcher})", disable=not progress, leave=False) as bar:
        if matcher == "sequential":
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = overlap
            pairing.loop_detection = False  # needs a vocabulary tree file, which cannot be had offline
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing, device=device)
        else:
            pycolmap.match_exhaustive(database, matching_options=matching, device=device)
        bar.update(1)
    return time.perf_counter() - start


def uses_gpu(requested: bool) -> bool:
    import pycolmap

    return requested and pycolmap.has_cuda


def run_sfm(image_dir: Path, names: list[str], sizes: list[tuple[int, int]], work: Path, options: SfmOptions,
            from_video: bool, progress: bool = True) -> SfmResult:
    import pycolmap
    from tqdm import tqdm

    threads = options.threads or os.cpu_count() or 1
    gpu = uses_gpu(options.use_gpu)
    database = work / "database.db"
    seconds: dict[str, float] = {}
    # One camera per image size: one phone or one video, so its intrinsics are shared and well constrained.
    # (pycolmap's single camera skips every image of another size than the first, with a log line easily missed.)
    seconds["features"] = extract_features(database, image_dir, by_size(names, sizes),
                                           camera_model=options.camera_model, per_image=False,
                                           max_size=options.max_size, threads=threads, gpu=gpu, progress=progress,
                                           mask_path=options.mask_path)
    matcher = choose_matcher(options.matcher, from_video, len(names))
    seconds["matching"] = match_features(database, matcher, overlap=options.overlap, threads=threads, gpu=gpu,
                                         progress=progress)

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = threads
    mapping.random_seed = 0
    sparse = work / "sparse"
    sparse.mkdir(exist_ok=True)
    start = time.perf_counter()
    with tqdm(total=len(names), desc="mapping", unit="image", disable=not progress, leave=False) as bar:
        models = pycolmap.incremental_mapping(database, image_dir, sparse, options=mapping,
                                              next_image_callback=lambda: bar.update(1))
    seconds["mapping"] = time.perf_counter() - start
    # Too few registered is the worker's error to raise: it first finds out which photos were left out and why.
    ranked = sorted(models.values(), key=lambda r: -r.num_reg_images())
    distinct = distinct_models([registered_names(model) for model in ranked])
    return SfmResult(ranked[0] if ranked else None, len(distinct), matcher, seconds, distinct or [set()])


def distinct_models(model_images: list[set[str]]) -> list[set[str]]:
    """Each model's images less those a larger one holds (mapping now and then ends with a small model of images
    already registered: 2 of the kept model's, in 2 runs of 10 on the same photos), without the models that leaves
    empty; largest first."""
    distinct: list[set[str]] = []
    for names in model_images:
        names = names.difference(*distinct)
        if names:
            distinct.append(names)
    return sorted(distinct, key=len, reverse=True)


def too_few(result: SfmResult, total: int) -> str | None:
    """The one-line error when the kept model has fewer than MIN_REGISTERED images; None when it has enough."""
    registered = len(result.model_images[0])
    return _too_few(registered, total, result.matcher) if registered < MIN_REGISTERED else None


def registered_names(reconstruction) -> set[str]:
    """The names of the images a pycolmap.Reconstruction registered."""
    return {reconstruction.images[image_id].name for image_id in reconstruction.reg_image_ids()}


def _camera_of(database: Path, image_name: str) -> int:
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        return db.read_image_with_name(image_name).camera_id
    finally:
        db.close()


def _too_few(registered: int, total: int, matcher: str) -> str:
    other = "exhaustive" if matcher == "sequential" else "sequential (if the images are in capture order)"
    return (f"structure from motion registered only {registered} of {total} images (at least {MIN_REGISTERED} are "
            f"needed); try --matcher {other}, photos with more overlap and texture, or a larger --sfm-max-size")


def describe_camera(camera) -> str:
    params = ", ".join(f"{p:.4g}" for p in camera.params)
    return f"{camera.model.name} {camera.width}x{camera.height} ({params})"


def describe_cameras(reconstruction) -> str:
    """Each camera of the model (one per image size) on one line."""
    cameras = list(reconstruction.cameras.values())
    text = "; ".join(describe_camera(camera) for camera in cameras)
    return text if len(cameras) == 1 else f"{len(cameras)} cameras, one per image size: {text}"
