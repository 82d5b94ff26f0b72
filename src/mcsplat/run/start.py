"""How a training run begins in its folder: new, resumed or refused. Rank 0 reads the folder once (config.json and the
checkpoint) and compares once what a resumed run is asked to continue with against what it was trained with.

A new run is refused in a folder that holds one (without --overwrite) and inside a scene folder. A resumed run needs
its checkpoint, as many processes as trained it, and every setting as it was trained: the checkpoint's copy of
config.json says what that was, and a value of config.json (edited by hand) or of the command line that differs is
refused, each in one line saying where it came from. The options whose field says `{"resume": "process"}` come from
the command line, those that say where the scene and the folder are ("place") may change, and the values a plan
makes again are left out (--budget's steps, schedules and cap, which config.json may hold a plan ahead; the growth
rate a --cap-max plans, which a new run of the command line would plan from its own start).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..config import TrainConfig, flat_options, options_given, process_options, resume_policy, to_jsonable, with_options
from ..errors import MCSplatError
from ..io.atomic import remove_stale_temporaries
from ..io.disk import writing_into
from ..io.lock import FolderLock
from ..planning import REPLANNED_KEYS, Plan, initial_plan, options_with_plan, settings_of
from .folder import CHECKPOINT, RunDir
from .scene import refuse_scene_folder, with_folders_absolute


@dataclass(frozen=True)
class RunStart:
    """What a run begins with, as rank 0 read it from the folder."""

    config: TrainConfig  # the options given (a new run), or the saved ones with this command line's process options
    plan: Plan | None = None  # the plan a resumed run continues (None: a new run plans its own)
    checkpoint: dict[str, Any] | None = None  # the state a resumed run continues from
    scene_named: Path | None = None  # where config.json says a resumed run's scene is
    scene_fingerprint: dict[str, Any] | None = None  # config.json's fingerprint of it (None: a folder older than it)


def train_lock(config: TrainConfig) -> FolderLock:
    """The lock a training run holds on its folder from `begin` to its end (the caller releases it)."""
    return FolderLock(RunDir(config.run_dir).lock_file, "mcsplat train")


def begin(config: TrainConfig, lock: FolderLock, world_size: int = 1) -> RunStart:
    """Make the run folder ready for `config` and take its `lock`; a resumed run's configuration, plan and checkpoint
    read back and compared with what the command line asks (`world_size` processes)."""
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
    if not config.resume:
        return RunStart(config)
    # A run killed while writing its checkpoint leaves the half-written temporary beside it.
    remove_stale_temporaries(run.checkpoint_file)
    remove_stale_temporaries(run.previous_checkpoint_file)
    saved, plan, fingerprint = run.read_run_record()
    check_resumable(plan, world_size)  # first: another number of processes is the reason to give
    checkpoint = run.read_checkpoint()
    if "optimizers" not in checkpoint:
        raise MCSplatError(f"{run.checkpoint_file} holds a model only (a merge of blocks), not the state a run "
                           f"continues from; it cannot be resumed")
    refuse_changes(config, given, saved, plan, checkpoint.get("config"), run.config_file)
    # This command line's process options; where the run is now (the folder may have been moved); a run begun with
    # --overwrite is resumed, not overwritten again.
    continuing = with_options(saved, **process_options(config), out=run.path, resume=True, overwrite=False)
    return RunStart(continuing, plan, checkpoint, Path(saved.data), fingerprint)


def refuse_changes(config: TrainConfig, given: frozenset[str], saved: TrainConfig, plan: Plan,
                   trained_record: dict[str, Any] | None, saved_file: Path) -> None:
    """The one comparison of a resume: each setting the checkpoint was trained with (its copy of config.json,
    `trained_record`; config.json's own in a checkpoint older than the copy) against config.json's (`saved`, `plan`)
    and, for the options this command line was `given`, against the command line's (`config`, fitted as a new run of
    it would be). A difference is refused, in one line per source, saying which value to put back."""
    on_file = flat_options(options_with_plan(saved, plan))
    trained = flat_options(settings_of(trained_record)) if trained_record else on_file
    typed = flat_options(to_jsonable(config))
    asked = flat_options(options_with_plan(config, initial_plan(config, plan.world_size)))
    edited, ignored = [], []
    for key in sorted(on_file, key=lambda key: (key != "strategy", key)):  # an edited strategy named first
        if resume_policy(key) or key.startswith("budget_plan."):
            continue
        # A setting newer than the checkpoint's copy (an option added since) was trained at config.json's value.
        was = trained.get(key, on_file[key])
        if on_file[key] != was and not (saved.budget is not None and key in REPLANNED_KEYS):
            edited.append(key)  # (--budget writes its new plans as it goes: config.json may be a plan ahead)
        if key not in given or _planned_anew(key, saved):
            continue
        if key == "steps" and saved.budget is not None:
            ignored.append(f"{option_text(key, config.steps)} (its --budget {saved.budget} plans them)")
        elif asked[key] != was:
            ignored.append(f"{option_text(key, typed[key])} (trained with {option_text(key, was)})")
    if edited:
        key = edited[0]
        raise MCSplatError(f"{saved_file}: {key} is {json.dumps(on_file[key])}, but {CHECKPOINT} was trained with "
                           f"{json.dumps(trained[key])}; put that value back, or start a new run with --overwrite")
    if ignored:
        raise MCSplatError(f"--resume continues the run with the options it was trained with ({saved_file}), so "
                           f"these would be ignored: {', '.join(ignored)}; leave them out, or start a new run with "
                           f"--overwrite or another --out")


def _planned_anew(key: str, saved: TrainConfig) -> bool:
    """Whether a new run of the command line would plan `key` anew, so that its value there says nothing of what the
    option asks: --budget plans the schedules, the cap and the resolution from its measurements (its --steps is
    said apart), a --cap-max (or the automatic cap) MCMC's growth rate from the initial count."""
    if saved.budget is not None:
        return key in REPLANNED_KEYS and key != "steps"
    return key == "mcmc.grow_rate" and (saved.cap_max is not None or saved.mcmc.auto_cap)


def option_text(key: str, value: Any) -> str:
    """An option as a command line gives it: ("steps", 60) -> --steps 60, ("pose_opt", False) -> --no-pose-opt."""
    owner, dot, name = key.rpartition(".")
    if isinstance(value, bool):
        return f"--{owner}{dot}{'' if value else 'no-'}{name.replace('_', '-')}"
    shown = " ".join(map(str, value)) if isinstance(value, (list, tuple)) else value
    return f"--{owner}{dot}{name.replace('_', '-')} {shown}"


def check_resumable(plan: Plan, world_size: int) -> None:
    if plan.world_size != world_size:
        raise MCSplatError(f"this run was trained with {plan.world_size} process(es), its step schedules and "
                           f"learning rates scaled for {plan.world_size} views per step; resume it with the same "
                           f"number of processes (torchrun --nproc-per-node ... x --nnodes ...)")


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


def folders_to_make(path: Path) -> list[Path]:
    """The folders `begin` would make for a run folder at `path`: it and its missing parents, deepest first."""
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
