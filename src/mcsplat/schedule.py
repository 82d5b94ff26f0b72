"""What the configuration says about a given step: the active SH degree (the other step schedules live with their
owners: the position learning rate in optim.py, refinement in the strategies)."""

from __future__ import annotations

from .config import TrainConfig


def sh_degree_at(config: TrainConfig, step: int) -> int:
    """The SH degree a step renders with (0-based step): one more every `sh_increase_every` steps, up to the
    model's degree, as 3DGS raises it at iterations 1000, 2000, 3000."""
    return min(step // config.sh_increase_every, config.model.sh_degree)


def final_sh_degree(config: TrainConfig, steps_done: int) -> int:
    """The SH degree of the last step taken, after `steps_done` steps: what a finished model is shown with."""
    return sh_degree_at(config, max(steps_done - 1, 0))
