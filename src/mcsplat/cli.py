"""The `mcsplat` command: one small dataclass per subcommand, each with a `run()`.

To add a subcommand, write its dataclass (the docstring is its help text, the field docstrings its options' help)
and add it to COMMANDS. Import heavy modules inside `run()`, so that `mcsplat --help` stays fast and quiet.
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Sequence

import tyro

from mcsplat.errors import MCSplatError

DESCRIPTION = ("mcsplat: 3D Gaussian Splatting trained with the MCMC method (Kheradmand et al., 2024), on CPU or "
               "NVIDIA GPU. Scene folders may be COLMAP, Blender/NeRF (transforms.json) or LLFF (poses_bounds.npy); "
               "the format is detected.")


@dataclass
class Info:
    """Load a scene folder and print a summary: format, train/test views, image size, SfM points, radius."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATA")]
    """Scene folder: COLMAP (sparse/0 + images/), Blender/NeRF (transforms_*.json) or LLFF (poses_bounds.npy)."""
    downscale: int = 1
    """Load images at 1/N resolution (uses images_N/ when the folder has it)."""
    test_every: int = 8
    """Every N-th view (sorted by name) is held out for testing; 0 = none. Blender test splits are kept as they are."""
    background: Annotated[str, tyro.conf.arg(metavar="COLOR")] = "auto"
    """'white', 'black' or 'r,g,b' in [0, 1]; 'auto' = white for Blender scenes, black otherwise."""

    def run(self) -> int:
        from mcsplat.data import load_scene

        background = None if self.background.strip().lower() == "auto" else self.background
        scene = load_scene(self.data, downscale=self.downscale, background=background, test_every=self.test_every)
        print(scene.summary())
        return 0


COMMANDS: dict[str, type] = {"info": Info}


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"mcsplat: warning: {' '.join(str(message).split())}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `mcsplat` console script. Returns the exit status (2 for a user error)."""
    command = tyro.extras.subcommand_cli_from_dict(COMMANDS, prog="mcsplat", description=DESCRIPTION,
                                                   args=list(sys.argv[1:] if argv is None else argv))
    previous = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        return command.run()
    except MCSplatError as exc:
        print(f"mcsplat: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mcsplat: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = previous


if __name__ == "__main__":
    sys.exit(main())
