"""A run folder: its layout, how a training run starts in it (new, resumed or refused), and how every other command
reads a trained run back (`load`).

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

import dataclasses
import functools
import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import torch

from .config import PROCESS_OPTIONS, TrainConfig, flat_options, options_given, process_options, to_jsonable
from .data import Scene, detect_kind
from .errors import DataError, MCSplatError
from .gaussians import DEAD_OPACITY, GaussianModel
from .io.atomic import atomic_path, atomic_write_text, remove_stale_temporaries
from .io.checkpoint import DamagedCheckpoint, load_checkpoint, save_checkpoint
from .io.disk import writing_into
from .io.lock import FolderLock
from .io.ply import write_ply
from .planning import (REPLANNED_KEYS, Plan, initial_plan, load_run_config, options_with_plan, save_run_config,
                       settings_of)
from .planning.config_file import load_scene_entry, save_scene_entry
from .run_scene import Background, background_of, scene_of, with_folders_absolute

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
# What --resume may change: the process options, and where the scene and the run folder now are.
RESUME_MAY_CHANGE = frozenset(PROCESS_OPTIONS) | {"data", "out", "resume", "overwrite"}



class RunDir:
    """The files of one run folder. Nothing here creates the folder but `prepare`."""

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
        holds a run (a new run's folder is locked by `prepare`)."""
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

    def read_checkpoint_of(self, config: TrainConfig, plan: Plan) -> dict[str, Any]:
        """The checkpoint that `config` and `plan` (config.json) resume from; refused when config.json no longer says
        what the checkpoint was trained with (edited by hand: another strategy, another SH degree...)."""
        state = self.read_checkpoint()
        if "optimizers" not in state:
            raise MCSplatError(f"{self.checkpoint_file} holds a model only (a merge of blocks), not the state a run "
                               f"continues from; it cannot be resumed")
        trained = flat_options(settings_of(state.get("config") or {}))
        now = flat_options(options_with_plan(config, plan))
        # --budget plans these as it goes and plans them again on resume: config.json may be a plan behind.
        planned = REPLANNED_KEYS if config.budget is not None else ()
        for key in sorted(trained.keys() & now.keys()):
            if key.split(".")[0] in RESUME_MAY_CHANGE or key in planned or key.startswith("budget_plan."):
                continue
            if trained[key] != now[key]:
                raise MCSplatError(f"{self.config_file}: {key} is {json.dumps(now[key])}, but {CHECKPOINT} was trained "
                                   f"with {json.dumps(trained[key])}; put that value back, or start a new run with "
                                   f"--overwrite")
        return state

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


# --------------------------------------------------------------------------------------------- starting a run
def train_lock(config: TrainConfig) -> FolderLock:
    """The lock a training run holds on its folder from `prepare` to its end (the caller releases it)."""
    return FolderLock(RunDir(config.run_dir).lock_file, "mcsplat train")


def prepare(config: TrainConfig, lock: FolderLock, world_size: int = 1) -> tuple[TrainConfig, Plan | None]:
    """Make the run folder ready for `config`, take its `lock`, and return the configuration to train with and the
    plan to continue: `config` itself and no plan for a new run; on --resume the run's saved configuration with this
    command line's process options, and its plan. A folder holding a run is refused without --resume or
    --overwrite, and a run resumed by another number of processes (`world_size`) than trained it."""
    config = with_folders_absolute(config)
    run = RunDir(config.run_dir)
    given = options_given(config)
    if config.budget is not None and "steps" in given:
        raise MCSplatError(f"--budget {config.budget} plans the steps itself, so --steps {config.steps} would be "
                           f"ignored; give one of them")
    if run.path.exists() and not run.path.is_dir():
        raise MCSplatError(f"--out {run.path}: exists and is not a directory")
    if config.resume:
        refuse_resume_without_checkpoint(run)
    else:
        refuse_scene_folder(run.path, Path(config.data))
        if run.holds_run() and not config.overwrite:
            refuse_folder_holding_a_run(run)
    with writing_into(run.path.parent):
        run.path.mkdir(parents=True, exist_ok=True)
    lock.acquire()
    if config.resume:
        # A run killed while writing its checkpoint leaves the half-written temporary beside it.
        remove_stale_temporaries(run.checkpoint_file)
        remove_stale_temporaries(run.previous_checkpoint_file)
    if not config.resume:
        return config, None
    saved, plan = run.read_plan()
    check_resumable(plan, world_size)  # first: another number of processes is the reason to give
    refuse_options_resume_ignores(config, given, saved, plan, run.config_file)
    # This command line's process options; where the run is now (the folder may have been moved).
    return dataclasses.replace(saved, **process_options(config), out=run.path, resume=True), plan


def refuse_resume_without_checkpoint(run: RunDir) -> None:
    if run.checkpoint_file.is_file():
        return
    if not run.holds_run():
        raise MCSplatError(f"--resume: {run.path} holds no run to continue (no {CHECKPOINT}); train without --resume "
                           f"to start one")
    # A run stopped (or killed) before its first checkpoint: nothing to continue from, only to start again.
    raise MCSplatError(f"--resume: {run.path} has no {CHECKPOINT} to continue from (its run stopped before writing "
                       f"one); start it again with --overwrite instead of --resume")


def refuse_folder_holding_a_run(run: RunDir) -> None:
    if run.checkpoint_file.is_file():
        raise MCSplatError(f"{run.path} already holds a run; pass --resume to continue it, --overwrite to replace its "
                           f"files, or --out to choose another directory")
    raise MCSplatError(f"{run.path} already holds a run with no {CHECKPOINT} to continue from (it stopped before "
                       f"writing one); pass --overwrite to start it again, or --out to choose another directory")


def refuse_options_resume_ignores(config: TrainConfig, given: frozenset[str], saved: TrainConfig, plan: Plan,
                                  saved_file: Path) -> None:
    """--resume continues a run with the options it was trained with (`saved`, with its `plan`): one that this
    command line (`config`) was `given` with another value would be ignored, so it is refused. The values are
    compared as a new run would have started with them (schedules fitted to the steps, scaled for the processes);
    --budget's plan, and the growth rate a --cap-max plans, are left out."""
    trained, typed = flat_options(options_with_plan(saved, plan)), flat_options(to_jsonable(config))
    now = flat_options(options_with_plan(config, initial_plan(config, plan.world_size)))
    if saved.budget is not None:
        planned = REPLANNED_KEYS - {"steps"}  # its --steps is said below
    else:
        planned = {"mcmc.grow_rate"} if saved.cap_max is not None or saved.mcmc.auto_cap else set()  # --cap-max's
    ignored = []
    for key in sorted(given & trained.keys()):
        if key.split(".")[0] in RESUME_MAY_CHANGE or key in planned:
            continue
        if key == "steps" and saved.budget is not None:
            ignored.append(f"{option_text(key, config.steps)} (its --budget {saved.budget} plans them)")
        elif now[key] != trained[key]:
            ignored.append(f"{option_text(key, typed[key])} (trained with {option_text(key, trained[key])})")
    if ignored:
        raise MCSplatError(f"--resume continues the run with the options it was trained with ({saved_file}), so "
                           f"these would be ignored: {', '.join(ignored)}; leave them out, or start a new run with "
                           f"--overwrite or another --out")


def option_text(key: str, value: Any) -> str:
    """An option as a command line gives it: ("steps", 60) -> --steps 60, ("pose_opt", False) -> --no-pose-opt."""
    owner, dot, name = key.rpartition(".")
    if isinstance(value, bool):
        return f"--{owner}{dot}{'' if value else 'no-'}{name.replace('_', '-')}"
    shown = " ".join(map(str, value)) if isinstance(value, (list, tuple)) else value
    return f"--{owner}{dot}{name.replace('_', '-')} {shown}"


def folders_to_make(path: Path) -> list[Path]:
    """The folders `prepare` would make for a run folder at `path`: it and its missing parents, deepest first."""
    path = Path(path).absolute()
    missing = []
    while not path.exists() and path != path.parent:
        missing.append(path)
        path = path.parent
    return missing


def remove_if_empty(folders: list[Path]) -> None:
    """Remove the folders a run refused before it began made (`folders_to_make`, deepest first): only while empty,
    so that nothing but what it made goes."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty (the run began, or someone wrote there), or gone already
            return


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


def check_resumable(plan: Plan, world_size: int) -> None:
    if plan.world_size != world_size:
        raise MCSplatError(f"this run was trained with {plan.world_size} process(es), its step schedules and "
                           f"learning rates scaled for {plan.world_size} views per step; resume it with the same "
                           f"number of processes (torchrun --nproc-per-node ... x --nnodes ...)")


# ------------------------------------------------------------------------------------------- a trained run
@dataclass
class TrainedRun:
    """A finished (or stopped) run, read back from its folder: what eval, render, export, view and report need."""

    folder: RunDir
    config: TrainConfig
    plan: Plan
    model: GaussianModel
    step: int  # steps done
    device: torch.device

    @property
    def sh_degree(self) -> int:
        """The SH degree the model was last trained with."""
        return self.plan.final_sh_degree(self.step)

    @functools.cached_property
    def scene(self) -> Scene:
        """The run's scene, loaded on first use (MCSplatError when its folder is gone or changed); a block's run
        finds its plan from where its folder is now."""
        return scene_of(dataclasses.replace(self.config, out=self.folder.path))

    @property
    def background(self) -> Background:
        return background_of(self.config, self.scene)


def load(path: str | Path, device: torch.device) -> TrainedRun:
    """The run in `path`: its configuration and the model of its checkpoint, on `device`."""
    folder = RunDir(path)
    config, plan = folder.read_plan()
    state = folder.read_checkpoint()
    model = GaussianModel.from_state_dict(state["model"]).to(device)
    model.antialiased = config.antialiased
    return TrainedRun(folder=folder, config=config, plan=plan, model=model, step=int(state["step"]), device=device)
