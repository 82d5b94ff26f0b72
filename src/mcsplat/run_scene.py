"""The scene of a run: loaded as the run loads it, named from the root in config.json with the folders it reads
beside it, known by its fingerprint wherever it is now (so --resume continues on the scene it trained on), and the
background it is composited on."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import warnings
from pathlib import Path
from typing import Any

from .config import TrainConfig
from .data import Scene, load_scene
from .data.attachments.depth import DepthOptions
from .data.attachments.masks import MaskOptions
from .errors import MCSplatError
from .partition import block_scene

Background = tuple[float, float, float]

# Options that name a folder unless they hold one of their words.
FOLDER_OPTIONS = {"masks": ("auto", "none", "alpha"), "depths": ("auto", "none")}


def scene_of(config: TrainConfig) -> Scene:
    """The scene a run trains on, loaded as the run loads it (a block's run: the part of it its block trains on)."""
    scene = load_scene(config.data, downscale=config.downscale, test_every=config.test_every,
                       background=None if config.background == "auto" else config.background,
                       masks=MaskOptions(config.masks, config.invert_masks),
                       attachments=[DepthOptions(config.depths, config.depth_encoding, config.depth_measure,
                                                 config.depth_png_step)])
    return scene if config.block is None else block_scene(scene, config.block, config.run_dir)


def with_folders_absolute(config: TrainConfig) -> TrainConfig:
    """`config` with its --masks and --depths folders from the root, as config.json names the scene (`absolute`):
    `eval` or --resume run from another folder still finds them. Their keywords stay as they are."""
    changes = {key: str(absolute(value)) for key, words in FOLDER_OPTIONS.items()
               if (value := getattr(config, key)) and value not in words}
    return dataclasses.replace(config, **changes) if changes else config


def absolute(path: str | Path) -> Path:
    """`path` from the root, as config.json names a scene: a command run from another folder still finds it (the
    path as typed, not resolved: a link to a scene stays one)."""
    return Path(os.path.abspath(path))


def scene_fingerprint(scene: Scene) -> dict[str, Any]:
    """What tells a scene from another wherever its folder is (config.json's "scene"): its kind, its training and
    test views' counts, and a digest of their names and image sizes."""
    digest = hashlib.sha256()
    for split, views in (("train", scene.train), ("test", scene.test)):
        for view in views:
            digest.update(f"{split}|{view.name}|{view.camera.width}x{view.camera.height}\n".encode())
    return {"kind": scene.kind, "train_views": len(scene.train), "test_views": len(scene.test),
            "views": digest.hexdigest()[:16]}


def scene_to_resume(config: TrainConfig, named: Path, saved: dict[str, Any] | None, config_file: Path
                    ) -> tuple[Scene, str | None]:
    """The scene a resumed run continues on: the one given (`config.data`) when it is the scene the run trained on
    (`saved`, config.json's fingerprint of it), wherever it is now, with a note when it is not where `config_file`
    names it (`named`); another scene is refused, saying where each path came from. A folder written before the
    fingerprint takes the scene config.json names, or, when that is gone, the one given, with a warning that it is
    unchecked."""
    given = Path(config.data)
    moved = given.resolve() != named.resolve()
    if saved is None and moved and named.exists():
        raise MCSplatError(f"--resume: this run trained on {named} ({config_file} names it), not on {given}; give "
                           f"that scene (this run folder is older than the fingerprint that would tell whether "
                           f"{given} holds the same scene)")
    scene = scene_of(config)
    if saved is None:
        if moved:
            warnings.warn(f"--resume: {config_file} names the scene {named}, which is gone; resuming on {given} "
                          f"without checking that it is the same scene (this run folder is older than the "
                          f"fingerprint that would tell)", stacklevel=3)
        return scene, None
    found = scene_fingerprint(scene)
    if found != saved:
        differs = scene_difference(found, saved)
        if not moved:
            raise MCSplatError(f"--resume: {given} is not the scene this run trained on: it has {differs} (the scene "
                               f"changed, or the path in {config_file} was edited); give the scene the run trained "
                               f"on, or start a new run with --overwrite or another --out")
        raise MCSplatError(f"--resume: {given} (given on the command line) is not the scene this run trained on, "
                           f"{named} ({config_file} names it): it has {differs}; give that scene, or train "
                           f"{given} in another --out")
    return scene, (f"on the scene given, {given} ({config_file} named {named}: the same views)" if moved
                   else None)


def scene_difference(found: dict[str, Any], saved: dict[str, Any]) -> str:
    """How the scene of fingerprint `found` differs from the one of `saved`, in words."""
    if found["kind"] != saved["kind"]:
        return f"the format {found['kind']}, where the run's scene is {saved['kind']}"
    if (found["train_views"], found["test_views"]) != (saved["train_views"], saved["test_views"]):
        return (f"{found['train_views']} training and {found['test_views']} test views, where the run's scene has "
                f"{saved['train_views']} and {saved['test_views']}")
    return "other view names or image sizes than the run's scene"


def background_of(config: TrainConfig, scene: Scene) -> Background:
    if config.background == "auto":
        return scene.background
    return (1.0, 1.0, 1.0) if config.background == "white" else (0.0, 0.0, 0.0)
