"""The `mcsplat` command: one small dataclass per subcommand, each with a `run_command()`, in the module of its kind
(scene.py: info, process; trained.py: what reads a trained run; blocks.py). `train` is TrainConfig itself
(config.py).

To add a subcommand, write its dataclass (the docstring is its help text, the field docstrings its options' help)
with a `run_command()` method and add it to COMMANDS. Import heavy modules inside `run_command()`, so that
`mcsplat --help` stays quick and quiet.
"""

from __future__ import annotations

import os
import sys

# OpenMP threads that spin after each torch op steal the cores the rasterizer's own threads need; let them sleep.
# Only effective before torch loads, hence here and not in the library.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import warnings  # noqa: E402
from typing import Sequence  # noqa: E402

import tyro  # noqa: E402

from ..config import TrainConfig  # noqa: E402
from ..errors import MCSplatError  # noqa: E402

from .blocks import blocks  # noqa: E402
from .scene import Info, Process  # noqa: E402
from .trained import Eval, Export, Render, Report, ViewSaved  # noqa: E402

DESCRIPTION = ("mcsplat: 3D Gaussian Splatting trained with the MCMC method (Kheradmand et al., 2024), on CPU or "
               "NVIDIA GPU. Scene folders may be COLMAP, Blender/NeRF (transforms.json) or LLFF (poses_bounds.npy); "
               "the format is detected.")

COMMANDS: dict[str, object] = {"train": TrainConfig, "eval": Eval, "render": Render, "export": Export,
                               "info": Info, "report": Report, "view": ViewSaved, "process": Process,
                               "blocks": blocks}


def _run(command, args: list[str]) -> int:
    if isinstance(command, TrainConfig):  # train, and blocks plan (whose blocks train with these options)
        from dataclasses import replace

        from ..config import named_options

        command = replace(command, named=named_options(args))  # what --resume and --budget check: the options given
    if type(command) is TrainConfig:
        from ..train import train  # the trainer pulls in Warp: only when training

        train(command)
        return 0
    return command.run_command()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"mcsplat: warning: {' '.join(str(message).split())}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `mcsplat` console script. Returns the exit status (2 for a user error)."""
    previous = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        args = list(sys.argv[1:] if argv is None else argv)
        command = tyro.extras.subcommand_cli_from_dict(COMMANDS, prog="mcsplat", description=DESCRIPTION, args=args)
        from ..stopping import signals_interrupt

        with signals_interrupt():  # SIGTERM and SIGHUP stop every command as Ctrl-C does
            return _run(command, args)
    except MCSplatError as exc:
        print(f"mcsplat: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mcsplat: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = previous
