"""The `mcsplat` command: one small dataclass per subcommand, each with a `run()`.

To add a subcommand, write its dataclass (the docstring is its help text, the field docstrings its options' help)
with a `run_command()` method and add it to COMMANDS. `train` is TrainConfig itself (config.py). Import heavy modules
inside `run_command()`, so that `mcsplat --help` stays quick and quiet.
"""

from __future__ import annotations

import os
import sys

# OpenMP threads that spin after each torch op steal the cores the rasterizer's own threads need; let them sleep.
# Only effective before torch loads, hence here and not in the library.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Sequence

import tyro

from mcsplat.config import TrainConfig
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

    def run_command(self) -> int:
        from mcsplat.data import load_scene

        background = None if self.background.strip().lower() == "auto" else self.background
        scene = load_scene(self.data, downscale=self.downscale, background=background, test_every=self.test_every)
        print(scene.summary())
        return 0


RunDir = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
Device = Literal["auto", "cpu", "cuda"]


@dataclass
class Eval:
    """Evaluate a trained run on its test views (PSNR, SSIM, LPIPS) and update its metrics.json."""

    run: RunDir
    """Run directory written by `mcsplat train`."""
    lpips_net: Literal["alex", "vgg"] | None = None
    """LPIPS backbone (default: the one the run was trained with)."""
    device: Device = "auto"
    save_renders: bool = False
    """Also write the test renders as PNG under RUN/renders/test/."""

    def run_command(self) -> int:
        import json

        from mcsplat.data import load_scene
        from mcsplat.io.atomic import atomic_write_text
        from mcsplat.trainer import background_of, evaluate, final_sh_degree, load_trained, resolve_device

        device = resolve_device(self.device)
        config, model, step = load_trained(self.run, device)
        scene = _scene_of(config)
        net = self.lpips_net or config.lpips_net
        result = evaluate(model, scene.test, background_of(config, scene), final_sh_degree(config, step), device,
                          lpips_net=net, render_dir=self.run / "renders" / "test" if self.save_renders else None,
                          progress=True)
        metrics_path = self.run / "metrics.json"
        metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
        metrics.update(psnr=result.psnr, ssim=result.ssim, lpips=result.lpips, lpips_net=net, steps=step,
                       num_gaussians=model.num_gaussians, test_views=result.views)
        atomic_write_text(metrics_path, json.dumps(metrics, indent=2) + "\n")
        lpips = "n/a (weights not installed)" if result.lpips is None else f"{result.lpips:.4f}"
        print(f"PSNR {result.psnr:.3f} dB  SSIM {result.ssim:.4f}  LPIPS-{net} {lpips}  "
              f"({result.views} test views, {model.num_gaussians:,} Gaussians, step {step:,})")
        return 0


@dataclass
class Render:
    """Render a trained run: the test (or train) views as PNG, or a video along a loop through the cameras."""

    run: RunDir
    """Run directory written by `mcsplat train`."""
    split: Literal["test", "train"] = "test"
    video: bool = False
    """Write an .mp4 along a smooth loop through the split's cameras instead of one PNG per view."""
    frames: int = 120
    """Video length in frames."""
    fps: int = 30
    out: Path | None = None
    """Output folder for PNGs or .mp4 path (default: RUN/renders/<split>/ or RUN/renders/<split>.mp4)."""
    device: Device = "auto"

    @staticmethod
    def _frame(model, camera, background, degree):
        import torch

        from mcsplat.render import render

        with torch.no_grad():
            return render(model, camera, background, degree).rgb

    def run_command(self) -> int:
        from tqdm import tqdm

        from mcsplat.camera_path import loop_path
        from mcsplat.trainer import background_of, final_sh_degree, load_trained, resolve_device, save_png

        if self.frames < 2 or self.fps < 1:
            raise MCSplatError("--frames must be at least 2 and --fps at least 1")
        device = resolve_device(self.device)
        config, model, step = load_trained(self.run, device)
        scene = _scene_of(config)
        views = scene.test if self.split == "test" else scene.train
        if not views:
            raise MCSplatError(f"the scene has no {self.split} views to render")
        background, degree = background_of(config, scene), final_sh_degree(config, step)
        if not self.video:
            folder = self.out or self.run / "renders" / self.split
            for view in tqdm(views, desc="rendering", unit="view"):
                image = self._frame(model, view.camera.to(device), background, degree)
                save_png(folder / f"{Path(view.name).stem}.png", image)
            print(f"wrote {len(views)} renders to {folder}")
            return 0
        import imageio.v2 as imageio

        from mcsplat.io.atomic import atomic_path

        path = self.out or self.run / "renders" / f"{self.split}.mp4"
        if path.suffix.lower() != ".mp4":
            raise MCSplatError(f"--out {path}: a video must be an .mp4 file")
        cameras = loop_path([v.camera for v in views], self.frames)
        with atomic_path(path) as tmp:
            with imageio.get_writer(tmp, format="FFMPEG", fps=self.fps, codec="libx264", quality=8,
                                    macro_block_size=1) as writer:
                for camera in tqdm(cameras, desc="video", unit="frame"):
                    image = self._frame(model, camera.to(device), background, degree)
                    writer.append_data((image.clamp(0, 1) * 255 + 0.5).byte().cpu().numpy())
        print(f"wrote {path} ({self.frames} frames at {self.fps} fps)")
        return 0


@dataclass
class Export:
    """Export a trained run's Gaussians in the standard 3DGS .ply layout (dead Gaussians left out)."""

    run: RunDir
    format: Literal["ply"] = "ply"
    out: Path | None = None
    """Output file (default: RUN/point_cloud.ply)."""

    def run_command(self) -> int:
        from mcsplat.trainer import export_ply, load_trained

        _, model, _ = load_trained(self.run, "cpu")
        path = self.out or self.run / "point_cloud.ply"
        count = export_ply(model, path)
        print(f"wrote {path} ({count:,} of {model.num_gaussians:,} Gaussians; dead ones left out)")
        return 0


def _scene_of(config):
    from mcsplat.data import load_scene

    return load_scene(config.data, downscale=config.downscale, test_every=config.test_every,
                      background=None if config.background == "auto" else config.background)


COMMANDS: dict[str, type] = {"train": TrainConfig, "eval": Eval, "render": Render, "export": Export,
                             "info": Info}


def _run(command) -> int:
    if isinstance(command, TrainConfig):
        from mcsplat.trainer import train  # the trainer pulls in Warp: only when training

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
        command = tyro.extras.subcommand_cli_from_dict(COMMANDS, prog="mcsplat", description=DESCRIPTION,
                                                       args=list(sys.argv[1:] if argv is None else argv))
        return _run(command)
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
