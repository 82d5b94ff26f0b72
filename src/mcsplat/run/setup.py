"""How a training run begins: its folder read once and prepared (new, resumed or refused: run/start.py), this
process's own options, its device and threads, the scene, the state (fresh or from the checkpoint), its planner, and
the folder's files begun.

The loop (trainer.TrainingRun) starts from what `set_up` gives it; with several processes every process sets up the
same way, rank 0 alone reading and writing the folder.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from . import folder as run_dir
from . import scene as run_scene
from . import start as run_start
from ..compute.device import resolve_device
from ..config import TrainConfig, feature_groups, process_options, with_options
from ..data import Scene
from ..distributed import Team, scene_summary, setup_of, threads_per_process
from ..features import features_named
from ..io.lock import FolderLock
from ..planning import Planner, initial_plan, planner_for
from ..render import set_cpu_threads
from .state import TrainingState, start


@dataclass
class RunSetup:
    config: TrainConfig  # what this process trains with: the run's configuration, this process's own options
    folder: run_dir.RunDir
    device: torch.device
    scene: Scene
    background: run_scene.Background
    state: TrainingState
    init_note: str  # where the state came from (the initialisation, or the step resumed at)
    planner: Planner


def set_up(config: TrainConfig, team: Team, lock: FolderLock) -> RunSetup:
    """Everything a run needs before its first step; rank 0 takes `lock` on the folder (the caller releases it)."""
    team.check_same_setup(setup_of(config))
    for group in features_named(feature_groups(config), "check_processes"):  # before the folder is touched
        group.check_processes(team.world_size)
    own = config
    begun = team.on_main(lambda: run_start.begin(own, lock, team.world_size))  # its refusal stops every process
    # This process's own options, and the scene given to it, from the root (it may differ between machines: the
    # scenes are compared below; a resumed run's with the one it trained on).
    config = with_options(begun.config, **process_options(own), data=run_scene.absolute(own.data))
    plan = begun.plan or initial_plan(config, team.world_size)
    folder = run_dir.RunDir(config.run_dir)
    device = team.device(resolve_device(config.device))
    threads = config.threads if config.threads is not None or team.world_size == 1 else threads_per_process()
    if threads is not None:
        torch.set_num_threads(threads)
    set_cpu_threads(threads)
    if config.resume and team.is_main:
        scene, scene_note = run_scene.scene_to_resume(config, begun.scene_named, begun.scene_fingerprint,
                                                      folder.config_file)
    else:
        scene, scene_note = run_scene.scene_of(config), None
    team.check_same_setup(scene_summary(scene))
    if not scene.test and config.eval_every and team.is_main:
        warnings.warn(f"--eval-every {config.eval_every} is ignored: the scene has no test views to evaluate "
                      f"(--test-every {config.test_every})", stacklevel=3)
    background = run_scene.background_of(config, scene)
    state, note = start(config, plan, scene, background, device, team, begun.checkpoint,
                        progress=not config.quiet and team.is_main)
    if scene_note:
        note = f"{note} {scene_note}"
    planner = planner_for(config, plan, scene, state, resumed=config.resume)
    if team.is_main:
        folder.begin(config, planner.plan, state.step, run_scene.scene_fingerprint(scene))
    return RunSetup(config, folder, device, scene, background, state, note, planner)
