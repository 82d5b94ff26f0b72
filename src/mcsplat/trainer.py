"""The training loop: schedules, progress, periodic evaluation, checkpoints and the run directory's outputs.

One step (SPEC 2, in gsplat's order, see strategy/mcmc.py for how the official code differs):
    render a training view -> loss = 0.8 L1 + 0.2 D-SSIM + strategy regularizers -> backward
    -> strategy.step_post_backward (ADC gradient statistics) -> Adam step for every parameter
    -> strategy.step_post_optimizer (MCMC: relocate / grow every 100 steps, then SGLD noise; ADC: densify / prune)
"""

from __future__ import annotations

import json
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from .config import TrainConfig, load_config, save_config, to_jsonable
from .data import Scene, View, load_scene
from .errors import MCSplatError
from .gaussians import GaussianModel
from .io.atomic import atomic_write, atomic_write_text, remove_stale_temporaries
from .io.checkpoint import load_checkpoint, save_checkpoint
from .io.ply import write_ply
from .losses import photometric_loss
from .metrics import LPIPS_HINT, lpips_model, psnr, ssim_metric
from .optim import make_optimizers, means_lr_at, set_means_lr
from .render import render, set_cpu_threads
from .strategy.adc import ADCStrategy
from .strategy.mcmc import MCMCStrategy

CHECKPOINT = "checkpoint.pt"
DEAD_OPACITY = 0.005  # Gaussians at or below it are dead (SPEC 5) and left out of the exported .ply
RUN_MARKERS = ("config.json", CHECKPOINT, "metrics.json", "point_cloud.ply")


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise MCSplatError("--device cuda: no CUDA device is available here; use --device cpu (or auto)")
    return torch.device(name)


def background_of(config: TrainConfig, scene: Scene) -> tuple[float, float, float]:
    if config.background == "auto":
        return scene.background
    return (1.0, 1.0, 1.0) if config.background == "white" else (0.0, 0.0, 0.0)


class ViewSampler:
    """Training views in random order, each once per pass (as 3DGS pops cameras from a shuffled copy)."""

    def __init__(self, count: int, seed: int):
        self.count = count
        self.generator = torch.Generator().manual_seed(seed)
        self.order: list[int] = []

    def next(self) -> int:
        if not self.order:
            self.order = torch.randperm(self.count, generator=self.generator).tolist()
        return self.order.pop()

    def state_dict(self) -> dict:
        return {"generator": self.generator.get_state(), "order": list(self.order)}

    def load_state_dict(self, state: dict) -> None:
        self.generator.set_state(state["generator"])
        self.order = list(state["order"])


def make_strategy(config: TrainConfig, scene_radius: float, generator: torch.Generator):
    if config.strategy == "mcmc":
        return MCMCStrategy(config.mcmc, scene_radius, generator)
    return ADCStrategy(config.adc, scene_radius, generator)


def initial_model(config: TrainConfig, scene: Scene, device: torch.device, generator: torch.Generator
                  ) -> tuple[GaussianModel, str]:
    m = config.model
    use_sfm = m.init == "sfm" or (m.init == "auto" and scene.points is not None and scene.kind != "blender")
    if use_sfm:
        if scene.points is None:
            raise MCSplatError(f"--model.init sfm: {scene.root} has no SfM points; use --model.init random")
        model = GaussianModel.from_points(scene.points, scene.point_colors, init_scale=m.init_scale,
                                          init_opacity=m.init_opacity, sh_degree=m.sh_degree, device=device)
        return model, f"SfM ({model.num_gaussians:,} points)"
    model = GaussianModel.random_init(scene.radius, blender=scene.kind == "blender", num_points=m.num_init_points,
                                      extent=m.init_extent, init_scale=m.init_scale, init_opacity=m.init_opacity,
                                      sh_degree=m.sh_degree, generator=generator, device=device)
    return model, f"random ({model.num_gaussians:,} points)"


@dataclass
class Evaluation:
    psnr: float
    ssim: float
    lpips: float | None
    lpips_net: str
    views: int


@torch.no_grad()
def evaluate(model: GaussianModel, views: list[View], background, sh_degree: int, device: torch.device,
             lpips_net: str | None = None, render_dir: Path | None = None, progress: bool = False) -> Evaluation:
    """Mean PSNR / SSIM / LPIPS over `views`; optionally writes each render as PNG into `render_dir`."""
    if not views:
        raise MCSplatError("no test views to evaluate: the scene has no test split (check --test-every)")
    lp = lpips_model(lpips_net, device=device) if lpips_net else None
    scores = {"psnr": [], "ssim": [], "lpips": []}
    for view in tqdm(views, desc="evaluating", disable=not progress, leave=False):
        target = view.image_float(device)
        image = render(model, view.camera.to(device), background, sh_degree).rgb.clamp(0, 1)
        scores["psnr"].append(psnr(image, target))
        scores["ssim"].append(ssim_metric(image, target))
        if lp is not None:
            scores["lpips"].append(float(lp(image, target)))
        if render_dir is not None:
            save_png(render_dir / f"{Path(view.name).stem}.png", image)
    return Evaluation(psnr=float(np.mean(scores["psnr"])), ssim=float(np.mean(scores["ssim"])),
                      lpips=float(np.mean(scores["lpips"])) if scores["lpips"] else None,
                      lpips_net=lpips_net or "", views=len(views))


def save_png(path: Path, image: torch.Tensor) -> None:
    pixels = (image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    atomic_write(path, lambda tmp: Image.fromarray(pixels).save(tmp, format="PNG"))


def export_ply(model: GaussianModel, path: Path) -> int:
    """The standard 3DGS .ply without dead Gaussians; returns how many were written."""
    return write_ply(path, dict(model.params.items()), keep=model.opacities.detach() > DEAD_OPACITY)


class _StopRequest:
    """Ctrl-C asks the loop to stop at the end of the current step (a second Ctrl-C stops at once)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = None

    def __enter__(self):
        def handler(signum, frame):
            if self.requested:
                raise KeyboardInterrupt
            self.requested = True
        try:
            self._previous = signal.signal(signal.SIGINT, handler)
        except ValueError:  # not the main thread: leave Ctrl-C alone
            self._previous = None
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


def _prepare_run_dir(config: TrainConfig) -> Path:
    run_dir = config.run_dir
    if run_dir.exists() and not run_dir.is_dir():
        raise MCSplatError(f"--out {run_dir}: exists and is not a directory")
    holds_run = run_dir.is_dir() and any((run_dir / m).exists() for m in RUN_MARKERS)
    if config.resume:
        if not (run_dir / CHECKPOINT).is_file():
            raise MCSplatError(f"--resume: {run_dir} has no {CHECKPOINT} to continue from")
        # A run killed while writing its checkpoint leaves the half-written temporary beside it.
        remove_stale_temporaries(run_dir / CHECKPOINT)
    elif holds_run and not config.overwrite:
        raise MCSplatError(f"{run_dir} already holds a run; pass --resume to continue it, --overwrite to replace its "
                           f"files, or --out to choose another directory")
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def train(config: TrainConfig) -> dict[str, Any]:
    """Run the whole job; returns the final metrics (also written to metrics.json)."""
    run_dir = _prepare_run_dir(config)
    if config.resume:
        saved = load_config(run_dir)
        # The saved configuration rules (steps included: the learning-rate schedule depends on it), except for what
        # only affects how this process runs.
        for key in ("eval_every", "save_every", "quiet", "threads", "device"):
            setattr(saved, key, getattr(config, key))
        saved.resume, config = True, saved
    device = resolve_device(config.device)
    if config.threads is not None:
        torch.set_num_threads(config.threads)
    set_cpu_threads(config.threads)
    log = (lambda *a: None) if config.quiet else (lambda *a: tqdm.write(" ".join(str(x) for x in a)))

    scene = load_scene(config.data, downscale=config.downscale, background=config.background
                       if config.background != "auto" else None, test_every=config.test_every)
    background = background_of(config, scene)
    torch.manual_seed(config.seed)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    sampler = ViewSampler(len(scene.train), config.seed)
    start_step, train_seconds = 0, 0.0

    if config.resume:
        state = load_checkpoint(run_dir / CHECKPOINT)
        model = GaussianModel.from_state_dict(state["model"]).to(device)
        optimizers = make_optimizers(model, config.optim, scene.radius)
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        strategy = make_strategy(config, scene.radius, generator)
        strategy.load_state_dict(state["strategy"])
        generator.set_state(state["generator"])
        sampler.load_state_dict(state["sampler"])
        start_step, train_seconds = state["step"], state["train_seconds"]
        init_note = f"resumed at step {start_step:,}"
    else:
        model, init_note = initial_model(config, scene, device, generator)
        optimizers = make_optimizers(model, config.optim, scene.radius)
        strategy = make_strategy(config, scene.radius, generator)
        save_config(config, run_dir / "config.json")
    log(f"mcsplat: {scene.kind} scene {scene.root.name}: {len(scene.train)} train / {len(scene.test)} test views, "
        f"{config.strategy} strategy, init {init_note}, {config.steps:,} steps on {device}")

    def checkpoint(step: int) -> None:
        save_checkpoint(run_dir / CHECKPOINT, {
            "step": step, "train_seconds": train_seconds, "model": model.state_dict(),
            "optimizers": {name: opt.state_dict() for name, opt in optimizers.items()},
            "strategy": strategy.state_dict(), "generator": generator.get_state(), "sampler": sampler.state_dict(),
            "config": to_jsonable(config)})

    log_file = run_dir / "log.jsonl"
    bar = tqdm(total=config.steps, initial=start_step, disable=config.quiet, dynamic_ncols=True, unit="step",
               mininterval=0.5)
    step = start_step
    counts: dict[str, int] = {}
    with _StopRequest() as stop:
        while step < config.steps:
            tick = time.perf_counter()
            means_lr = means_lr_at(step, config.steps, config.optim, scene.radius)
            set_means_lr(optimizers, means_lr)
            sh_degree = min(step // config.sh_increase_every, config.model.sh_degree)
            view = scene.train[sampler.next()]
            target = view.image_float(device)
            camera = view.camera.to(device)
            result = render(model, camera, background, sh_degree)
            loss = photometric_loss(result.rgb, target, config.ssim_weight) + strategy.regularization(model)
            if not torch.isfinite(loss):
                raise MCSplatError(f"step {step}: the loss became {loss.item()}; lower the learning rates or check "
                                   f"the input images (the last checkpoint is kept)")
            loss.backward()
            strategy.step_post_backward(step, model, result, camera.width, camera.height)
            for opt in optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
            # The noise uses the position learning rate after this step's decay, as gsplat does (SPEC 13).
            info = strategy.step_post_optimizer(step, model, optimizers,
                                                means_lr_at(step + 1, config.steps, config.optim, scene.radius))
            for key, value in info.items():  # counts since the last log record (relocated, added, pruned, ...)
                if key != "num_gaussians":
                    counts[key] = counts.get(key, 0) + int(value)
            step += 1
            train_seconds += time.perf_counter() - tick

            train_psnr = psnr(result.rgb.detach(), target)
            bar.update(1)
            if step % 10 == 0 or step == config.steps:
                bar.set_postfix(loss=f"{loss.item():.4f}", psnr=f"{train_psnr:.2f}", gaussians=model.num_gaussians,
                                refresh=False)
            record = None
            if step % 100 == 0 or step == config.steps:
                record = {"step": step, "loss": round(loss.item(), 6), "train_psnr": round(train_psnr, 3),
                          "num_gaussians": model.num_gaussians, "elapsed_seconds": round(train_seconds, 2)}
                record.update(counts)
                counts = {}
            if config.eval_every and step % config.eval_every == 0 and step < config.steps:
                result_eval = evaluate(model, scene.test, background, sh_degree, device)
                record = (record or {"step": step, "num_gaussians": model.num_gaussians,
                                     "elapsed_seconds": round(train_seconds, 2)})
                record.update(test_psnr=round(result_eval.psnr, 3), test_ssim=round(result_eval.ssim, 4))
                log(f"step {step:,}: test PSNR {result_eval.psnr:.2f} dB, SSIM {result_eval.ssim:.4f}, "
                    f"{model.num_gaussians:,} Gaussians")
            if record is not None:
                with open(log_file, "a") as f:
                    f.write(json.dumps(record) + "\n")
            if config.save_every and step % config.save_every == 0 and step < config.steps:
                checkpoint(step)
            if stop.requested:
                bar.close()
                checkpoint(step)
                raise MCSplatError(f"stopped at step {step:,}; the checkpoint is saved: continue with "
                                   f"`mcsplat train {config.data} --out {run_dir} --resume`")
    bar.close()
    checkpoint(step)

    final_degree = final_sh_degree(config, step)
    evaluation = evaluate(model, scene.test, background, final_degree, device, lpips_net=config.lpips_net,
                          render_dir=run_dir / "renders" / "test" if config.save_renders else None,
                          progress=not config.quiet)
    exported = export_ply(model, run_dir / "point_cloud.ply")
    metrics = {"psnr": evaluation.psnr, "ssim": evaluation.ssim, "lpips": evaluation.lpips,
               "lpips_net": config.lpips_net, "num_gaussians": model.num_gaussians, "exported_gaussians": exported,
               "steps": step, "train_seconds": round(train_seconds, 2), "device": str(device),
               "strategy": config.strategy, "test_views": evaluation.views, "sh_degree": final_degree}
    atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    lpips_text = f"{evaluation.lpips:.4f}" if evaluation.lpips is not None else "n/a"
    log(f"test PSNR {evaluation.psnr:.2f} dB, SSIM {evaluation.ssim:.4f}, LPIPS-{config.lpips_net} {lpips_text} "
        f"on {evaluation.views} views; {model.num_gaussians:,} Gaussians, {train_seconds:.0f} s of training")
    if evaluation.lpips is None:
        log(f"hint: {LPIPS_HINT}")
    log(f"wrote {run_dir / 'point_cloud.ply'} ({exported:,} Gaussians) and {run_dir / 'metrics.json'}")
    return metrics


def load_trained(run_dir: Path, device: torch.device) -> tuple[TrainConfig, GaussianModel, int]:
    """(config, model, step) of a finished or interrupted run, from its checkpoint."""
    config = load_config(run_dir)
    state = load_checkpoint(Path(run_dir) / CHECKPOINT)
    return config, GaussianModel.from_state_dict(state["model"]).to(device), int(state["step"])


def final_sh_degree(config: TrainConfig, step: int) -> int:
    return min(max(step - 1, 0) // config.sh_increase_every, config.model.sh_degree)
