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
from typing import Annotated, Literal, Sequence, Union

import tyro

from mcsplat.config import TrainConfig
from mcsplat.errors import MCSplatError
from mcsplat.gaussians import DEAD_OPACITY
from mcsplat.export import FORMAT_NAMES, format_help

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
    """'white', 'black' or 'r,g,b' in [0, 1]; 'auto' = white when the images have an alpha channel, else black."""
    masks: str = "auto"
    """Training masks: 'auto' (the scene's masks/ folder when it has one), 'none', 'alpha' or a folder."""
    invert_masks: bool = False
    """Masks are white where the pixel is left out."""

    def run_command(self) -> int:
        from mcsplat.data import load_scene
        from mcsplat.data.attachments.masks import MaskOptions
        from mcsplat.initialization import start_without_points

        background = None if self.background.strip().lower() == "auto" else self.background
        scene = load_scene(self.data, downscale=self.downscale, background=background, test_every=self.test_every,
                           masks=MaskOptions(self.masks, self.invert_masks))
        print(scene.summary(start=start_without_points(scene)))
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
        from mcsplat import run_dir
        from mcsplat.compute.device import resolve_device
        from mcsplat.evaluation import evaluate
        from mcsplat.run_metrics import metrics

        with run_dir.RunDir(self.run).lock("mcsplat eval"):
            run = run_dir.load(self.run, resolve_device(self.device))
            net = self.lpips_net or run.config.lpips_net
            render_file = (lambda name: run.folder.render_file("test", name)) if self.save_renders else None
            result = evaluate(run.model, run.scene.test, run.background, run.sh_degree, run.device, lpips_net=net,
                              render_file=render_file, progress=True)
            run.folder.update_metrics(**metrics(result, net, run.step, run.model.num_gaussians))
        lpips = "n/a (weights not installed)" if result.lpips is None else f"{result.lpips:.4f}"
        print(f"PSNR {result.psnr:.3f} dB  SSIM {result.ssim:.4f}  LPIPS-{net} {lpips}  "
              f"({result.views} test views, {run.model.num_gaussians:,} Gaussians, step {run.step:,})")
        if run.config.appearance != "none":
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

        from mcsplat.render import render

        with torch.no_grad():
            return render(model, camera, background, degree).rgb

    def run_command(self) -> int:
        import contextlib

        from mcsplat import run_dir
        from mcsplat.compute.device import resolve_device

        if self.frames < 2 or self.fps < 1:
            raise MCSplatError("--frames must be at least 2 and --fps at least 1")
        run = run_dir.load(self.run, resolve_device(self.device))
        if self.out is not None:
            run_dir.refuse_writing_into_scene(self.out, run.config)
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

        from mcsplat import run_dir
        from mcsplat.evaluation import save_png

        for view in tqdm(views, desc="rendering", unit="view"):
            image = self._frame(run.model, view.camera.to(run.device), run.background, run.sh_degree)
            save_png(run_dir.render_file(folder, view.name), image)
        print(f"wrote {len(views)} renders to {folder}")

    def _video(self, run, views, path: Path) -> None:
        import imageio.v2 as imageio
        from tqdm import tqdm

        from mcsplat.camera_path import loop_path
        from mcsplat.data.images import uint8_pixels
        from mcsplat.io.atomic import atomic_path

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
    # Its choices and help come from the table of export formats (export/formats.py): a new format adds no line here.
    format: Annotated[Literal[FORMAT_NAMES] | None, tyro.conf.arg(help=format_help())] = None
    out: Path | None = None
    """Output file, named .ply, .splat, .compressed.ply, .spz, .sog, .glb or .gltf (default: RUN/point_cloud.<that
    ending>); with --format mesh, .ply, .glb or .obj (default: RUN/mesh.ply)."""
    min_opacity: float = DEAD_OPACITY
    """Leave out Gaussians of this opacity or less (0.005: the dead ones MCMC relocates)."""
    max_gaussians: int | None = None
    """Keep at most N: those that contribute most (opacity x largest cross-section)."""
    prune: bool = False
    """Also leave out the Gaussians composited into no pixel of any training view (needs the run's scene), and
    print the test PSNR with and without them."""
    max_scale: float | None = None
    """Leave out Gaussians whose largest axis exceeds this many scene radii (the training cameras' extent): viewers
    draw very large splats badly. Prints the test PSNR with and without them."""
    max_distance: float | None = None
    """Leave out Gaussians farther than this many scene radii from the training cameras' centre: very far splats
    leave viewers that sort by depth too little precision for the scene. Prints the test PSNR with and without."""
    spz_version: Literal[3, 4] = 3
    """spz: 3 (gzip, read by every .spz reader) or 4 (zstd, a little smaller; splat-transform and three.js read it,
    Spark 2.2 does not)."""
    voxel_size: float | None = None
    """mesh: edge of a voxel of the fusion volume, in scene units (default: the finest the budget allows)."""
    voxel_budget: int = 1 << 24
    """mesh: voxels of the fusion volume at most (memory: about 16 bytes each)."""
    alpha_min: float = 0.5
    """mesh: pixels whose accumulated alpha stays below this show no surface and fuse nothing."""
    min_component: float = 0.02
    """mesh: drop connected pieces of fewer faces than this share of the largest piece's (0 keeps all)."""
    depth: Literal["median", "planar"] = "median"
    """mesh: the depth each view fuses: median (where the ray meets the Gaussian at which alpha reaches 0.5) or
    planar (where it meets the composited plane of flat Gaussians; for runs trained with --surface)."""
    truncation: float = 4.0
    """mesh: half-width of the signed distance band, in voxels. 16-24 suits a clean object (synthetic, or masked):
    the views' depths of a surface disagree a little, and a narrow band leaves the mesh slightly inside it; on a
    capture with floaters a wide band lets them pull the mesh outward (docs/outputs.md)."""
    consistent_views: int = 4
    """mesh: fuse a pixel's depth only where at least this many of the 6 nearest training views see the same
    surface there (within 1% of its depth): floaters and stray depths are left out. 0 fuses every pixel."""
    device: Device = "auto"

    def run_command(self) -> int:
        from dataclasses import asdict

        from mcsplat.export import ExportOptions, export_run

        options = asdict(self)
        export_run(options.pop("run"), ExportOptions(**options))
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
        from mcsplat.report import make_report
        from mcsplat.report.views import saved_run_views

        import contextlib

        from mcsplat.run_dir import RunDir, refuse_writing_into_scene

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
        from mcsplat.viewer import require_viser

        require_viser()
        from mcsplat.compute.device import resolve_device
        from mcsplat.viewer.saved import view_saved

        if not self.path.exists():
            raise MCSplatError(f"{self.path}: no such run directory or .ply file")
        try:
            view_saved(self.path, self.host, self.port, resolve_device(self.device), origins=self.viewer_origin)
        except KeyboardInterrupt:
            print("mcsplat: viewer stopped", file=sys.stderr)
        return 0


@dataclass
class Process:
    """Photos or a video to a scene folder that `mcsplat train` loads: pycolmap SIFT features, matching, incremental
    mapping, then undistortion to SCENE/images + SCENE/sparse/0 (PINHOLE). No COLMAP binary needed."""

    input: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="INPUT")]
    """A folder of photos (jpg/png, any names) or a video file (mp4/mov)."""
    out: Path
    """The scene folder to write (created; an existing scene is only replaced with --overwrite)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """auto: sequential for a video's frames, exhaustive for photos."""
    num_frames: int | None = None
    """Video: how many frames to keep, the sharpest of each stretch (default 200)."""
    fps: float | None = None
    """Video: frames to keep per second of video, instead of --num-frames."""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE"] = "SIMPLE_RADIAL"
    """Lens model estimated by SfM, one camera shared by all images (SIMPLE_RADIAL: COLMAP's default, steadier than
    OPENCV on few or small images)."""
    sfm_max_size: int = 1600
    """SIFT runs on images shrunk to at most this many pixels on the long side (the scene keeps full size)."""
    threads: int | None = None
    """CPU threads for pycolmap (default: all cores)."""
    overwrite: bool = False
    masks: Path | None = None
    """Photos only: a folder of masks (<photo name>.png, black: leave out, as `mcsplat train --masks`): SIFT finds no
    features where they leave out (people, sky, the operator), and the scene gets them, undistorted, as masks/."""
    invert_masks: bool = False
    """The masks are white where the photo is to be left out."""
    min_registered: float | None = None
    """Stop, writing no scene, when fewer than this share of the photos register (0.8: four in five); which photos
    were left out and why is printed (and written to process.json) either way."""

    def run_command(self) -> int:
        import math

        from mcsplat.capture import ProcessOptions, process

        if self.num_frames is not None and self.num_frames < 3 or \
                self.fps is not None and not (self.fps > 0 and math.isfinite(self.fps)):
            raise MCSplatError("--num-frames must be at least 3 and --fps a positive finite number")
        if self.invert_masks and self.masks is None:
            raise MCSplatError("--invert-masks without --masks: there are no masks to invert; give the masks' folder "
                               "with --masks, or leave --invert-masks out")
        summary = process(self.input, self.out, ProcessOptions(
            matcher=self.matcher, camera_model=self.camera_model, sfm_max_size=self.sfm_max_size,
            num_frames=self.num_frames, fps=self.fps, threads=self.threads, overwrite=self.overwrite,
            masks=None if self.masks is None else str(self.masks), invert_masks=self.invert_masks,
            min_registered=self.min_registered))
        print("\n".join(summary.lines()))
        return 0


BlocksFolder = Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="OUT")]


@dataclass(frozen=True)
class BlocksPlan(TrainConfig):
    """Cut a scene into blocks that train as independent runs and merge into one model (docs/blocks.md): blocks on
    the ground plane with equal shares of the SfM points, each with the views that see it and a share of --cap-max.
    Writes OUT/blocks.json (read it, edit it) and shows each block's views, cap and estimated memory. Takes every
    option of `mcsplat train`: each block trains with them."""

    out: Path | None = None
    """The blocks folder (default: runs/<scene folder name>-blocks)."""
    overwrite: bool = False
    """Plan again into a blocks folder that holds a plan (refused while it holds block runs trained to it)."""
    # What the plan refuses is hidden: `blocks train OUT` resumes the blocks a stop left, `view OUT/block_NN` shows one.
    resume: Annotated[bool, tyro.conf.Suppress] = False
    viewer: Annotated[bool, tyro.conf.Suppress] = False
    port: Annotated[int, tyro.conf.Suppress] = 8080
    host: Annotated[str, tyro.conf.Suppress] = "127.0.0.1"
    viewer_origin: Annotated[tuple[str, ...], tyro.conf.Suppress] = ()
    count: int | None = None
    """Number of blocks (default: the fewest that fit --memory)."""
    memory: str | None = None
    """Memory each block's run may hold, e.g. 16GiB: blocks whose estimate exceeds it are refused before training."""
    margin: float = 0.2
    """Each block trains on the points of its cell grown by this share of its size on each side."""
    min_view_share: float = 0.25
    """A view trains a block when at least this share of the points it sees lie in the block's region."""

    def run_command(self) -> int:
        import dataclasses

        from mcsplat.blocks import plan_blocks
        from mcsplat.partition import parse_bytes

        training = TrainConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(TrainConfig)})
        out = self.out or Path("runs") / f"{Path(self.data).resolve().name}-blocks"
        plan_blocks(training, out, count=self.count, memory=None if self.memory is None else parse_bytes(self.memory),
                    margin=self.margin, min_view_share=self.min_view_share, overwrite=self.overwrite)
        return 0


@dataclass
class BlocksTrain:
    """Train the blocks of OUT/blocks.json, each as an ordinary run in OUT/block_NN/ (a trained block is kept, a
    stopped one resumes), then merge them into OUT/merged/. Under torchrun each process trains its share of the
    blocks and rank 0 merges; --block I trains one block only (one job of a job array), without merging."""

    out: BlocksFolder
    """Blocks folder written by `mcsplat blocks plan`."""
    block: int | None = None
    """Train this block only."""
    device: Device = "auto"
    threads: int | None = None
    """CPU threads of each block's run (default: all cores, shared between torchrun's processes)."""
    quiet: bool = False

    def run_command(self) -> int:
        from mcsplat.blocks import train_blocks
        from mcsplat.partition import BlocksFolder as Folder

        train_blocks(Folder(self.out), None if self.block is None else [self.block], device=self.device,
                     threads=self.threads, quiet=self.quiet)
        return 0


@dataclass
class BlocksMerge:
    """Merge the trained blocks of OUT into OUT/merged/: each block's Gaussians inside its own cell, one run folder
    that eval, render, export, view and report read, scored on all the scene's test views."""

    out: BlocksFolder
    """Blocks folder written by `mcsplat blocks plan`."""
    device: Device = "auto"
    quiet: bool = False

    def run_command(self) -> int:
        from mcsplat.blocks import merge_blocks
        from mcsplat.partition import BlocksFolder as Folder

        merge_blocks(Folder(self.out), device=self.device, quiet=self.quiet)
        return 0


Blocks = Union[Annotated[BlocksPlan, tyro.conf.subcommand("plan")],
               Annotated[BlocksTrain, tyro.conf.subcommand("train")],
               Annotated[BlocksMerge, tyro.conf.subcommand("merge")]]


def blocks(command: Annotated[Blocks, tyro.conf.OmitSubcommandPrefixes]) -> BlocksPlan | BlocksTrain | BlocksMerge:
    """A scene too large for one run, as blocks (docs/blocks.md): plan them (blocks.json), train each as a run of its
    own, merge them into one model."""
    return command  # a function rather than the Union itself: its docstring is the help of `mcsplat blocks`


COMMANDS: dict[str, object] = {"train": TrainConfig, "eval": Eval, "render": Render, "export": Export,
                               "info": Info, "report": Report, "view": ViewSaved, "process": Process,
                               "blocks": blocks}


def _run(command, args: list[str]) -> int:
    if isinstance(command, TrainConfig):  # train, and blocks plan (whose blocks train with these options)
        from dataclasses import replace

        from mcsplat.config import named_options

        command = replace(command, named=named_options(args))  # what --resume and --budget check: the options given
    if type(command) is TrainConfig:
        from mcsplat.train import train  # the trainer pulls in Warp: only when training

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
        from mcsplat.stopping import signals_interrupt

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


if __name__ == "__main__":
    sys.exit(main())
