"""The commands that read a trained run folder: eval, render, export, report and view."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from ..errors import MCSplatError
from ..export import ExportOptions

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
        from ..run import folder as run_dir
        from ..run import trained as trained_run
        from ..compute.device import resolve_device
        from ..run.evaluation import evaluate
        from ..run.metrics import metrics

        with run_dir.RunDir(self.run).lock("mcsplat eval"):
            run = trained_run.load(self.run, resolve_device(self.device))
            net = self.lpips_net or run.config.lpips_net
            render_file = (lambda name: run.folder.render_file("test", name)) if self.save_renders else None
            result = evaluate(run.model, run.scene.test, run.background, run.sh_degree, run.device, lpips_net=net,
                              render_file=render_file, progress=True)
            run.folder.update_metrics(**metrics(result, net, run.step, run.model.num_gaussians))
        lpips = "n/a (weights not installed)" if result.lpips is None else f"{result.lpips:.4f}"
        print(f"PSNR {result.psnr:.3f} dB  SSIM {result.ssim:.4f}  LPIPS-{net} {lpips}  "
              f"({result.views} test views, {run.model.num_gaussians:,} Gaussians, step {run.step:,})")
        if run.config.compensation.appearance != "none":
            print(f"compensated: PSNR {result.compensated_psnr:.3f} dB  SSIM {result.compensated_ssim:.4f}  (each "
                  "test view's colour transform fitted on its left half, the right half scored)")
        if result.masked_views:
            print(f"masked: PSNR {result.masked_psnr:.3f} dB  SSIM {result.masked_ssim:.4f}  "
                  f"({result.masked_views} views, over the pixels their masks keep)")
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

        from ..render import render

        with torch.no_grad():
            return render(model, camera, background, degree).rgb

    def run_command(self) -> int:
        import contextlib

        from ..run import scene as run_scene
        from ..run import trained as trained_run
        from ..compute.device import resolve_device

        if self.frames < 2 or self.fps < 1:
            raise MCSplatError("--frames must be at least 2 and --fps at least 1")
        run = trained_run.load(self.run, resolve_device(self.device))
        if self.out is not None:
            run_scene.refuse_writing_into_scene(self.out, run.config)
        views = run.scene.test if self.split == "test" else run.scene.train
        if not views:
            raise MCSplatError(f"the scene has no {self.split} views to render")
        if self.video and len(views) < 2:
            other = "train" if self.split == "test" else "test"
            raise MCSplatError(f"--video: a camera path needs at least two cameras, and the {self.split} split has "
                               f"one; render its image without --video, or the path through --split {other}")
        target = self.out or (run.folder.video_file if self.video else run.folder.renders_folder)(self.split)
        if self.video and target.suffix.lower() != ".mp4":
            raise MCSplatError(f"--out {target}: a video must be an .mp4 file")
        with run.folder.lock("mcsplat render") if run.folder.contains(target) else contextlib.nullcontext():
            (self._video if self.video else self._pngs)(run, views, target)
        return 0

    def _pngs(self, run, views, folder: Path) -> None:
        from tqdm import tqdm

        from ..run import folder as run_dir
        from ..run.evaluation import save_png

        for view in tqdm(views, desc="rendering", unit="view"):
            image = self._frame(run.model, view.camera.to(run.device), run.background, run.sh_degree)
            save_png(run_dir.render_file(folder, view.name), image)
        print(f"wrote {len(views)} renders to {folder}")

    def _video(self, run, views, path: Path) -> None:
        import imageio.v2 as imageio
        from tqdm import tqdm

        from ..flythrough import loop_path
        from ..data.images import uint8_pixels
        from ..io.atomic import atomic_path

        cameras = loop_path([v.camera for v in views], self.frames)
        with atomic_path(path) as tmp:
            with imageio.get_writer(tmp, format="FFMPEG", fps=self.fps, codec="libx264", quality=8,
                                    macro_block_size=1) as writer:
                for camera in tqdm(cameras, desc="video", unit="frame"):
                    image = self._frame(run.model, camera.to(run.device), run.background, run.sh_degree)
                    writer.append_data(uint8_pixels(image))
        print(f"wrote {path} ({self.frames} frames at {self.fps} fps)")


@dataclass
class Export:
    """Export a trained run's Gaussians for viewers: the 3DGS .ply, antimatter15 .splat, PlayCanvas compressed .ply
    or Niantic .spz, leaving out near-transparent Gaussians; or its surface as a triangle mesh."""

    run: RunDir
    export: Annotated[ExportOptions, tyro.conf.OmitArgPrefixes] = field(default_factory=ExportOptions)

    def run_command(self) -> int:
        from ..export import export_run

        export_run(self.run, self.export)
        return 0


@dataclass
class Report:
    """Make a run's report.html again (plots of quality, loss, Gaussians, refinement, opacity/scale distributions,
    step time; worst test views), or compare several runs on the same plots."""

    runs: Annotated[list[Path], tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
    """One run directory, or several to compare."""
    out: Path | None = None
    """Folder for report.html and plots/ (default: the run directory; required to compare runs)."""
    device: Device = "auto"

    def run_command(self) -> int:
        import contextlib

        from ..report import make_report
        from ..report.views import saved_run_views
        from ..run.folder import RunDir
        from ..run.scene import refuse_writing_into_scene

        if self.out is not None:
            for run in map(RunDir, self.runs):
                if run.config_file.is_file():
                    refuse_writing_into_scene(self.out, run.read_config())
        target = RunDir(self.out or self.runs[0])
        with target.lock("mcsplat report") if target.config_file.is_file() else contextlib.nullcontext():
            test_views, render_view = (), None
            if len(self.runs) == 1:
                test_views, render_view = saved_run_views(self.runs[0], self.device)
            page = make_report(self.runs, out=self.out, test_views=test_views, render_view=render_view)
        print(f"wrote {page}")
        return 0


@dataclass
class ViewSaved:
    """Look at a trained run (or any 3DGS .ply, or an exported .glb / .gltf of Gaussians) in the browser: our
    rasterizer renders what you point the camera at.
    A mesh (`mcsplat export --format mesh`'s .ply, .glb or .obj) the browser draws itself. Needs
    `pip install mcsplat[viewer]`. Stop with Ctrl-C."""

    path: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN|PLY|MESH")]
    """Run directory written by `mcsplat train`, a 3DGS .ply file, a .glb / .gltf of Gaussians, or a mesh file."""
    port: int = 8080
    host: str = "127.0.0.1"
    """Address to listen on; 0.0.0.0 exposes the viewer to the network."""
    viewer_origin: tuple[str, ...] = ()
    """Web pages (host names or origins such as http://myhost:8080) allowed to connect besides the viewer's own page:
    where it is reached under a name, or through a proxy."""
    device: Device = "auto"

    def run_command(self) -> int:
        from ..viewer import require_viser

        require_viser()
        from ..compute.device import resolve_device
        from ..viewer.saved import view_saved

        if not self.path.exists():
            raise MCSplatError(f"{self.path}: no such run directory or .ply file")
        try:
            view_saved(self.path, self.host, self.port, resolve_device(self.device), origins=self.viewer_origin)
        except KeyboardInterrupt:
            print("mcsplat: viewer stopped", file=sys.stderr)
        return 0


