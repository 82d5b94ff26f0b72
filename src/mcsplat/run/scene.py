"""The scene of a run: loaded as the run loads it, named from the root in config.json with the folders it reads
beside it, known by its fingerprint wherever it is now (so --resume continues on the scene it trained on), the
background it is composited on, and the rule that nothing is written inside a scene folder."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import warnings
from pathlib import Path
from typing import Any

from ..config import TrainConfig, feature_groups, with_options
from ..data import Scene, detect_kind, load_scene
from ..errors import DataError, MCSplatError
from ..features import features_named
from ..partition import block_scene

Background = tuple[float, float, float]



def scene_of(config: TrainConfig) -> Scene:
    """The scene a run trains on, loaded as the run loads it (a block's run: the part of it its block trains on)."""
    scene = load_scene(config.data, downscale=config.downscale, test_every=config.test_every,
                       background=None if config.background == "auto" else config.background,
                       attachments=[group.per_view_input()
                                    for group in features_named(feature_groups(config), "per_view_input")])
    return scene if config.block is None else block_scene(scene, config.block, config.run_dir)


def with_folders_absolute(config: TrainConfig) -> TrainConfig:
    """`config` with the folders its options name (--masks, --depths: a field whose metadata says "folder_unless" it
    holds one of its words) from the root, as config.json names the scene (`absolute`): `eval` or --resume run from
    another folder still finds them. Their keywords stay as they are."""
    changes = {f.name: str(absolute(value)) for group in feature_groups(config) for f in dataclasses.fields(group)
               if "folder_unless" in f.metadata and (value := getattr(group, f.name))
               and value not in f.metadata["folder_unless"]}
    return with_options(config, **changes) if changes else config


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


def scene_holding(path: Path) -> tuple[Path, str] | None:
    """The nearest folder at or above `path` that holds a scene, and its kind; None where none does
    (OTHER/images/a/b/x.ply lies inside the scene OTHER as well)."""
    for folder in (path, *path.parents):
        if folder.is_dir():
            try:
                return folder, detect_kind(folder)
            except DataError:
                continue
    return None


def refuse_scene_folder(out: Path, data: Path) -> None:
    """A run folder is never a scene folder, nor inside the scene it trains on or any other: mcsplat writes nothing
    there."""
    out, data = out.resolve(), data.resolve()
    if out == data or out.is_relative_to(data):
        raise MCSplatError(f"--out {out} is inside the scene folder {data}, which mcsplat never writes into; give "
                           f"a run folder elsewhere (the default is runs/{data.name} in the current folder)")
    held = scene_holding(out)
    if held is not None:
        folder, kind = held
        where = "holds" if folder == out else f"is inside {folder}, which holds"
        raise MCSplatError(f"--out {out} {where} a {kind} scene, which mcsplat never writes into; give another run "
                           f"folder")


def refuse_writing_into_scene(path: Path, config: TrainConfig) -> None:
    """An output of a command on a run (export, render, report) is never inside the scene the run trained on, nor
    in another scene folder: mcsplat writes nothing there."""
    target, data = path.resolve(), Path(config.data).resolve()
    if target == data or target.is_relative_to(data):
        raise MCSplatError(f"--out {path} is inside the scene folder {data} the run trained on, which mcsplat never "
                           f"writes into; write it elsewhere (leave --out out to write into the run folder)")
    held = scene_holding(target)
    if held is not None:
        raise MCSplatError(f"--out {path} is inside the scene folder {held[0]} (a {held[1]} scene), which mcsplat "
                           f"never writes into; write it elsewhere")
