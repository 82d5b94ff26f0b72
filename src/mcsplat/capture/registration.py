"""Which photos structure from motion left out, and the likely reason for each, from what the pipeline already knows.

Runs in the SfM worker after mapping: the features' database gives each photo's SIFT features and its verified
matches (two-view geometries) with every other photo, the models give who registered where, and a small decoded
copy of each photo its sharpness (variance of the Laplacian), its brightness and its contrast. A photo's figures are
judged against the registered photos' median, so that a dim or soft capture as a whole is not blamed photo by photo.
"""

from __future__ import annotations

import os
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from .frames import sharpness

MIN_INLIERS = 15          # COLMAP's min_num_inliers: a pair with fewer verified matches does not count as overlapping
BLUR_SHARE = 0.25         # blurred: sharpness under this share of the registered photos' median
FEW_FEATURES_SHARE = 0.25  # little texture: fewer SIFT features than this share of the median (or MIN_FEATURES)
MIN_FEATURES = 100
EXPOSURE_LEVELS = 60      # badly exposed: mean grey level this far (of 255) from the registered photos' median
FLAT_SHARE = 0.1          # featureless: contrast under this share of the median (a blur keeps the contrast of shapes)
ANALYSIS_SIZE = 640       # photos are measured on a copy at least this wide (JPEG draft decoding: fast)
MEDIAN = "the registered photos' median"  # what a left-out photo's figures are held against
EXIF_MAKE, EXIF_MODEL = 0x010F, 0x0110

# The causes, most telling first: a photo's first cause is its reason; the capture's commonest gets the suggestion.
# (A flat frame has no sharpness and no features either, whatever its level: featureless is judged first. A dark
# photo has little contrast, so a low sharpness too: exposure is judged before blur.)
SUGGESTIONS = {
    "separate model": "take more photos between the parts, so that each overlaps its neighbours by about two thirds",
    "featureless": "leave out frames that show nothing (a lens cap, a blank wall, sky or screen, a frame of the "
                   "ground), or take them again with the scene in view",
    "exposure": "fix the exposure (lock it on the phone) so that every photo is lit alike",
    "blur": "hold the camera still or move it more slowly (in low light, add light)",
    "texture": "frame fewer plain or reflective surfaces (walls, glass, screens); keep some texture in every photo",
    "camera": "take the whole capture with one camera at one zoom and size",
    "overlap": "take more photos with more overlap (each sharing about two thirds with the next), all of the scene",
    "pose": "take more photos with more overlap around the ones left out, from a little further apart",
}
LABELS = {"separate model": "in a separate model", "featureless": "featureless", "exposure": "badly exposed",
          "blur": "blurred",
          "texture": "with little texture", "camera": "from another camera", "overlap": "with no overlap",
          "pose": "with no pose"}


@dataclass
class PhotoFigures:
    """What the pipeline knows of one photo."""

    name: str
    features: int        # SIFT features found
    best_matches: int    # the most verified matches with any one registered photo
    best_matches_any: int  # the most verified matches with any one other photo, registered or not
    sharpness: float     # variance of the Laplacian on a reduced copy (measure())
    brightness: float    # mean grey level, 0-255
    camera: str          # EXIF make and model (when the photo has them) and size
    other_model: int = 0  # the size of the other model that registered it (0: none)
    contrast: float = 0.0  # spread of the grey levels over their mean (measure()): 0 for one flat tone


@dataclass
class LeftOut:
    """A photo that is not in the kept model: its reason (the likeliest cause) and the other causes found."""

    name: str
    reason: str          # a key of SUGGESTIONS
    detail: str          # the reason in words, with the figures behind it
    other_causes: list[str]
    figures: dict


def measure(path: Path) -> tuple[float, float, float]:
    """(sharpness, brightness, contrast) of the photo at `path`, on a reduced copy: a JPEG is decoded at the nearest
    scale at least ANALYSIS_SIZE wide, and frames.sharpness takes every n-th pixel of a wider one (640 to 1,280 px).
    Contrast is the grey levels' standard deviation over their mean: a darker copy of a photo keeps it."""
    with Image.open(path) as im:
        im.draft("RGB", (ANALYSIS_SIZE, ANALYSIS_SIZE * im.size[1] // max(1, im.size[0])))
        pixels = np.asarray(im.convert("RGB"))
    grey = pixels.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return sharpness(pixels), float(grey.mean()), float(grey.std() / max(float(grey.mean()), 1.0))


def camera_of(path: Path, size: tuple[int, int]) -> str:
    """"Make Model WxH" (the EXIF make and model where the photo has them)."""
    try:
        with Image.open(path) as im:
            exif = im.getexif()
        maker = " ".join(str(exif.get(tag, "")).strip("\x00 ") for tag in (EXIF_MAKE, EXIF_MODEL)).strip()
    except Exception:  # EXIF is a hint, never a reason to fail
        maker = ""
    return f"{maker + ' ' if maker else ''}{size[0]}x{size[1]}"


def diagnose(photos: list[PhotoFigures], registered: set[str]) -> tuple[list[LeftOut], dict[str, float]]:
    """The left-out photos (those not in `registered`) with their reasons, and the medians they are judged against:
    those of the registered photos (what worked; photos of something else mixed in do not shift them)."""
    reference = [p for p in photos if p.name in registered] or photos
    medians = {"features": float(np.median([p.features for p in reference])),
               "sharpness": float(np.median([p.sharpness for p in reference])),
               "brightness": float(np.median([p.brightness for p in reference])),
               "contrast": float(np.median([p.contrast for p in reference]))}
    usual_camera = Counter(p.camera for p in reference).most_common(1)[0][0]
    left_out = []
    for photo in photos:
        if photo.name in registered:
            continue
        causes = _causes(photo, medians, usual_camera)
        left_out.append(LeftOut(photo.name, causes[0][0], causes[0][1], [cause for cause, _ in causes[1:]],
                                {k: v for k, v in asdict(photo).items() if k != "name"}))
    return left_out, medians


def _causes(photo: PhotoFigures, medians: dict[str, float], usual_camera: str) -> list[tuple[str, str]]:
    """Every cause that applies to a left-out photo, most telling first (there is always at least one). A photo
    that another model registered was sharp and lit enough for SfM: what kept it out is that model's link."""
    causes = []
    if photo.other_model:
        causes.append(("separate model", f"in a separate model of {photo.other_model} photos that shares too "
                                         "little with the kept one"))
    flat = photo.contrast < FLAT_SHARE * medians["contrast"]  # then no sharpness and no features say nothing more
    if flat:
        causes.append(("featureless", f"featureless: nearly one flat tone (contrast {photo.contrast:.3f}, {MEDIAN} "
                                      f"{medians['contrast']:.3f}), nothing to match"))
    if abs(photo.brightness - medians["brightness"]) > EXPOSURE_LEVELS:
        light = "too dark" if photo.brightness < medians["brightness"] else "too bright"
        causes.append(("exposure", f"{light}: mean level {photo.brightness:.0f} of 255, {MEDIAN} "
                                   f"{medians['brightness']:.0f}"))
    if photo.sharpness < BLUR_SHARE * medians["sharpness"] and not flat:
        causes.append(("blur", f"blurred: sharpness {photo.sharpness:.0f}, {MEDIAN} "
                               f"{medians['sharpness']:.0f}"))
    if photo.features < max(MIN_FEATURES, FEW_FEATURES_SHARE * medians["features"]) and not flat:
        causes.append(("texture", f"little texture: {photo.features} features, {MEDIAN} "
                                  f"{medians['features']:.0f}"))
    if photo.camera != usual_camera:
        causes.append(("camera", f"another camera: {photo.camera}, most photos {usual_camera}"))
    if photo.best_matches < MIN_INLIERS:
        elsewhere = (f"; it matches only photos left out (up to {photo.best_matches_any}): does it show something "
                     "else?" if photo.best_matches_any >= MIN_INLIERS else "")
        causes.append(("overlap", f"overlaps no registered photo: at most {photo.best_matches} verified matches "
                                  f"with one ({MIN_INLIERS} needed){elsewhere}"))
    if not causes:
        causes.append(("pose", f"matched ({photo.best_matches} verified matches with a registered photo) but its "
                               "pose could not be fixed from them"))
    return causes


def suggestion(left_out: list[LeftOut]) -> str:
    """One plain suggestion, for the commonest reason (the most telling one on a tie); '' when none is left out."""
    if not left_out:
        return ""
    counts = Counter(photo.reason for photo in left_out)
    order = list(SUGGESTIONS)
    commonest = min(counts, key=lambda reason: (-counts[reason], order.index(reason)))
    return SUGGESTIONS[commonest]


def by_reason(left_out: list[LeftOut], shown: int = 4) -> str:
    """'2 blur (a.jpg, b.jpg); 1 overlap (c.jpg)', the commonest reason first, at most `shown` names each."""
    groups: dict[str, list[str]] = {}
    for photo in left_out:
        groups.setdefault(photo.reason, []).append(photo.name)
    parts = []
    for reason, names in sorted(groups.items(), key=lambda item: -len(item[1])):
        more = f" and {len(names) - shown} more" if len(names) > shown else ""
        parts.append(f"{len(names)} {LABELS[reason]} ({', '.join(names[:shown])}{more})")
    return "; ".join(parts)


def figures_from_database(database: Path, folder: Path, names: list[str], sizes: list[tuple[int, int]],
                          models: list[set[str]]) -> list[PhotoFigures]:
    """Each photo's figures: features and verified matches from COLMAP's `database`, sharpness and brightness from
    the photo in `folder`. `models`: the image names of each model SfM found, the kept one first."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        images = {image.name: image.image_id for image in db.read_all_images()}
        features = {name: db.num_keypoints_for_image(image_id) for name, image_id in images.items()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    names_of = {image_id: name for name, image_id in images.items()}
    kept = models[0] if models else set()
    best: dict[str, int] = {}
    best_any: dict[str, int] = {}
    for pair_id, count in zip(pair_ids, inliers):
        first, second = (names_of.get(i) for i in pycolmap.pair_id_to_image_pair(pair_id))
        for one, other in ((first, second), (second, first)):
            best_any[one] = max(best_any.get(one, 0), int(count))
            if other in kept:  # overlap with what registered is what counts for a left-out photo
                best[one] = max(best.get(one, 0), int(count))
    other_model = {name: len(model) for model in models[1:] for name in model}
    with ThreadPoolExecutor(max_workers=min(8, os.cpu_count() or 1), thread_name_prefix="mcsplat-report") as pool:
        measured = list(pool.map(lambda name: measure(folder / name), names))
    return [PhotoFigures(name, features.get(name, 0), best.get(name, 0), best_any.get(name, 0), round(sharp, 1),
                         round(bright, 1), camera_of(folder / name, size), other_model.get(name, 0),
                         round(contrast, 4))
            for name, size, (sharp, bright, contrast) in zip(names, sizes, measured)]
