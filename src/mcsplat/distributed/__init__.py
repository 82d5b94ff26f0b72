"""Training one model with several processes (torchrun): replicated data parallelism, N views per step.

`join()` returns this process's team (SingleProcess when it runs alone); the trainer drives the same loop either way.
The learning rates and step schedules of N processes are the plan's (planning/processes.py).
"""

from .setup import scene_summary, setup_of
from .team import (CHECK_EVERY, ProcessGroup, SingleProcess, command_for, join, parameter_checksum,
                   threads_per_process)

Team = SingleProcess | ProcessGroup  # the processes training one model (one, or torchrun's)

__all__ = ["CHECK_EVERY", "ProcessGroup", "SingleProcess", "Team", "command_for", "join", "parameter_checksum",
           "scene_summary", "setup_of", "threads_per_process"]
