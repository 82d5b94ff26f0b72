"""A run folder's layout, and its files read and written: how a run starts in it is run/start.py, a trained run read
back run/trained.py.

    RUN/config.json          the options as given and the plan (what --resume continues with), the scene's fingerprint
    RUN/checkpoint.pt        model, Adam state, strategy state, RNG states, step (written atomically, checksummed)
    RUN/checkpoint.prev.pt   the checkpoint before it (what to fall back to when checkpoint.pt is damaged)
    RUN/log.jsonl            a record every 100 steps and at each periodic evaluation
    RUN/metrics.json         the final (or last `mcsplat eval`) scores and counts
    RUN/point_cloud.ply      the trained Gaussians, dead ones left out
    RUN/mesh.ply             `mcsplat export --format mesh`'s surface (the report shows it when it is there)
    RUN/renders/<split>/     the test renders as PNG (and `mcsplat render`'s output; <split>.mp4 its video)
    RUN/report.html, plots/  the run report
    RUN/.lock                while a command writes the folder: who it is (io/lock.py)

Only this module spells out these names; everything else asks a RunDir for them.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path, PurePosixPath
from typing import Any

import torch

from ..config import TrainConfig
from ..errors import MCSplatError
from ..gaussians import DEAD_OPACITY, GaussianModel
from ..io.atomic import atomic_path, atomic_write_text
from ..io.checkpoint import DamagedCheckpoint, load_checkpoint, save_checkpoint
from ..io.lock import FolderLock
from ..io.ply import write_ply
from ..planning import Plan, load_run_config, save_run_config
from ..planning.config_file import load_run_record, load_scene_entry, save_scene_entry

CONFIG = "config.json"
CHECKPOINT = "checkpoint.pt"
PREVIOUS_CHECKPOINT = "checkpoint.prev.pt"
LOG = "log.jsonl"
METRICS = "metrics.json"
SPLATS = "point_cloud.ply"
MESH = "mesh.ply"
RENDERS = "renders"
REPORT = "report.html"
PLOTS = "plots"
LOCK = ".lock"
MARKERS = (CONFIG, CHECKPOINT, METRICS, SPLATS)  # any of them: the folder holds a run


class RunDir:
    """The files of one run folder. Nothing here creates the folder (run_start.begin does)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.config_file = self.path / CONFIG
        self.checkpoint_file = self.path / CHECKPOINT
        self.previous_checkpoint_file = self.path / PREVIOUS_CHECKPOINT
        self.log_file = self.path / LOG
        self.metrics_file = self.path / METRICS
        self.splats_file = self.path / SPLATS
        self.mesh_file = self.path / MESH
        self.report_file = self.path / REPORT
        self.plots_folder = self.path / PLOTS
        self.lock_file = self.path / LOCK

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    def export_file(self, ending: str) -> Path:
        """Where `mcsplat export` writes a format by default: point_cloud<ending> (".ply", ".spz", ...)."""
        return self.path / (Path(SPLATS).stem + ending)

    def renders_folder(self, split: str) -> Path:
        return self.path / RENDERS / split

    def video_file(self, split: str) -> Path:
        """Where `mcsplat render --video` writes the loop through a split's cameras."""
        return self.path / RENDERS / f"{split}.mp4"

    def render_file(self, split: str, view_name: str) -> Path:
        """Where a view's render is written: RUN/renders/<split>/<view's name>.png."""
        return render_file(self.renders_folder(split), view_name)

    def holds_run(self) -> bool:
        return self.path.is_dir() and any((self.path / marker).exists() for marker in MARKERS)

    def own_files(self) -> list[Path]:
        """The files that hold the run's state and records: no command's output may replace them."""
        return [self.config_file, self.checkpoint_file, self.previous_checkpoint_file, self.log_file,
                self.metrics_file, self.report_file, self.lock_file]

    def is_own_file(self, path: str | Path) -> bool:
        return Path(path).resolve() in {own.resolve() for own in self.own_files()}

    def contains(self, path: str | Path) -> bool:
        return Path(path).resolve().is_relative_to(self.path.resolve())

    def lock(self, command: str) -> FolderLock:
        """The folder's writer lock for `command` (`with run.lock("mcsplat eval"): ...`); only for a folder that
        holds a run (a new run's folder is locked by `run_start.begin`)."""
        if not self.config_file.is_file():
            self.read_config()  # the one-line "not a run directory" error
        return FolderLock(self.lock_file, command)

    # --------------------------------------------------------------------------------------------- reading
    def read_config(self) -> TrainConfig:
        return self.read_plan()[0]

    def read_plan(self) -> tuple[TrainConfig, Plan]:
        """The configuration the run trains with, and its plan (config.json)."""
        if not self.config_file.is_file():
            raise MCSplatError(f"{self.path}: not a run directory (no {CONFIG}); train one with `mcsplat train DATA`")
        return load_run_config(self.config_file)

    def read_scene_fingerprint(self) -> dict[str, Any] | None:
        """The fingerprint of the scene the run trains on (config.json; `scene_fingerprint`), or None in a folder
        written before it."""
        return load_scene_entry(self.config_file)

    def read_run_record(self) -> tuple[TrainConfig, Plan, dict[str, Any] | None]:
        """config.json read once: the configuration, its plan and the fingerprint of its scene (None in a folder
        written before it)."""
        if not self.config_file.is_file():
            self.read_plan()  # the one-line "not a run directory" error
        return load_run_record(self.config_file)

    def read_checkpoint(self) -> dict[str, Any]:
        try:
            return load_checkpoint(self.checkpoint_file)
        except DamagedCheckpoint as error:
            if self.previous_checkpoint_file.is_file():
                advice = (f"go back to the checkpoint before it with `mv {self.previous_checkpoint_file} "
                          f"{self.checkpoint_file}`, or start again with --overwrite")
            else:
                advice = "there is no older checkpoint to go back to; start again with --overwrite"
            raise MCSplatError(f"{error}; {advice}") from None

    def read_metrics(self) -> dict[str, Any]:
        """metrics.json, or {} before the run has finished once."""
        if not self.metrics_file.is_file():
            return {}
        try:
            return json.loads(self.metrics_file.read_text())
        except json.JSONDecodeError as error:
            raise MCSplatError(f"{self.metrics_file}: not valid JSON ({error}); delete it and run `mcsplat eval "
                               f"{self.path}` to write it again") from None

    # --------------------------------------------------------------------------------------------- writing
    def write_config(self, config: TrainConfig, plan: Plan, scene: dict[str, Any] | None = None) -> None:
        """config.json, with the fingerprint of the run's scene: `scene`, or else the one the file holds (--budget
        writes its plan again as the run goes)."""
        if scene is None and self.config_file.is_file():
            scene = self.read_scene_fingerprint()
        save_run_config(self.config_file, config, plan, scene)

    def begin(self, config: TrainConfig, plan: Plan, step: int, scene: dict[str, Any]) -> None:
        """The run's files as training starts at `step`, once its set-up has succeeded, on the scene of fingerprint
        `scene`. A new run writes its configuration and empties the log; with --overwrite it also removes the old
        run's checkpoints, which a --resume of the new configuration must not continue from. A resumed run cuts the
        log back to its checkpoint's step (a run killed between two checkpoints logged steps that will now be
        trained again), and config.json names its scene where it is now."""
        if config.resume:
            self.cut_log(step)
            save_scene_entry(self.config_file, config.data, scene)
            return
        self.write_config(config, plan, scene)
        self.cut_log(0)
        for old in (self.checkpoint_file, self.previous_checkpoint_file):
            old.unlink(missing_ok=True)

    def cut_log(self, step: int) -> None:
        """Keep the log's records up to `step` (and drop a line cut short by a kill)."""
        if not self.log_file.is_file():
            return
        kept = [line for line in self.log_file.read_text().splitlines(keepends=True)
                if line.endswith("\n") and _logged_step(line) <= step]
        atomic_write_text(self.log_file, "".join(kept))

    def write_checkpoint(self, state: dict[str, Any]) -> None:
        """checkpoint.pt, the one it replaces kept as checkpoint.prev.pt (a hard link made before the write, so that
        checkpoint.pt never stops existing)."""
        if self.checkpoint_file.is_file():
            keep_as_previous(self.checkpoint_file, self.previous_checkpoint_file)
        save_checkpoint(self.checkpoint_file, state)

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        atomic_write_text(self.metrics_file, json.dumps(metrics, indent=2) + "\n")

    def update_metrics(self, **values: Any) -> dict[str, Any]:
        """metrics.json with `values` replaced (the other keys kept); returns what was written."""
        metrics = {**self.read_metrics(), **values}
        self.write_metrics(metrics)
        return metrics

    def export_splats(self, model: GaussianModel) -> int:
        """point_cloud.ply: the standard 3DGS .ply without dead Gaussians; returns how many were written."""
        return write_ply(self.splats_file, dict(model.params.items()), keep=alive(model))


def _logged_step(line: str) -> float:
    """The step of a log record; infinity for a line that is not one (so that cutting the log drops it)."""
    try:
        return float(json.loads(line)["step"])
    except (ValueError, KeyError, TypeError):
        return math.inf


def keep_as_previous(current: Path, previous: Path) -> None:
    """Make `previous` the same file as `current` (replacing it in one step), or a copy where links are not
    allowed."""
    with atomic_path(previous) as tmp:
        tmp.unlink()
        try:
            os.link(current, tmp)
        except OSError:
            shutil.copyfile(current, tmp)


def render_file(folder: Path, view_name: str) -> Path:
    """A view's render inside `folder`: the view's name (its image's path in the scene, without the extension) as a
    PNG, sub-folders kept, so that two images of one name in two sub-folders keep two renders. Parts that would lead
    out of `folder` are left out."""
    parts = [part for part in PurePosixPath(view_name.replace("\\", "/")).parts if part not in ("/", ".", "..")]
    return folder.joinpath(*parts[:-1], f"{parts[-1] if parts else 'view'}.png")


def alive(model: GaussianModel) -> torch.Tensor:
    """[N] bool: the Gaussians an export keeps (opacity above DEAD_OPACITY)."""
    return model.opacities.detach() > DEAD_OPACITY
