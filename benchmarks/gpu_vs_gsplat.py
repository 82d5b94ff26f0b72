"""mcsplat against gsplat on one GPU: the same scene, initial Gaussians, views, schedule, loss and cap, MCMC on both.

    python benchmarks/gpu_vs_gsplat.py --data PATH/TO/lego --cap 300000 --steps 5000 [--init 150000]

Both arms run the same loop over the same view order, from the same random initialisation (mcsplat's, seed 0):
    mcsplat   mcsplat.step.Step, the trainer's own step (Warp rasterizer, mcsplat's MCMC strategy)
    mcsplat-graph  the same step replayed as a CUDA graph (mcsplat.graphed_step, `train --cuda-graph`)
    gsplat    gsplat.rasterization (packed=False, classic, eps2d 0.3, as gsplat's simple_trainer) and
              gsplat.strategy.MCMCStrategy, called after the Adam step as simple_trainer does
Shared by both: one fused torch Adam per parameter with mcsplat's learning rates (the paper's), the position rate's
log-linear decay, 0.8 L1 + 0.2 D-SSIM (mcsplat.losses) plus the 0.01 opacity and scale regularizers, SH degree +1 every
1,000 steps, refinement every 100 steps from 500 to 25,000 with growth of 5% up to the cap.

Printed per arm: median ms per step (the device synchronised around each step) over the last --timed steps, peak GPU
memory (torch.cuda.max_memory_allocated over the training), test PSNR / SSIM (each arm's own renderer, final SH
degree), the Gaussian count, and every 1,000 steps (--dead-every) the share of Gaussians at or below the dead
opacity just before the refinement relocates them (dead_share: MCMC's health; a share that keeps rising ends with
nearly all dead). JSON lines and a table go to --out (default benchmarks/results/gpu_vs_gsplat).
gsplat JIT-compiles its CUDA extension at first use: it needs nvcc and ninja; TORCH_CUDA_ARCH_LIST limits the targets.
"""

from __future__ import annotations

import mcsplat  # noqa: F401  (first: it lets torch's OpenMP threads sleep, see mcsplat/__init__.py)

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

import _common as C
from mcsplat.config import ModelConfig, TrainConfig
from mcsplat.data import load_scene
from mcsplat.graphed_step import graphed
from mcsplat.losses import photometric_loss
from mcsplat.metrics import psnr, ssim_metric
from mcsplat.optim import make_optimizers, means_lr_at, set_means_lr, update_for
from mcsplat.render import render
from mcsplat.initialization import initial_model
from mcsplat.run.scene import background_of
from mcsplat.planning import Plan, make_strategy
from mcsplat.run.state import ViewSampler
from mcsplat.step import Step


@dataclass(frozen=True)
class Training:
    """What is trained, and where (gpu_vs_gsplat.py's and step_profile.py's options)."""

    data: str
    """A scene folder (lego 400 in the benchmarks' figures)."""
    cap: int = 300_000
    """--cap-max of the training."""
    init: int | None = None
    """Random initial points (default: cap / 2; with SfM points these are used instead)."""
    init_method: Literal["auto", "random"] = "auto"
    """random: --init random points also for a capture with SfM points (to reach a large cap within the run)."""
    device: Literal["cuda", "cpu"] = "cuda"
    """cuda, or cpu (for gpu_vs_gsplat.py it only checks the script, with the mcsplat arm: gsplat needs CUDA)."""

    @property
    def initial_points(self) -> int:
        """--init, or half the cap."""
        return self.init or self.cap // 2


@dataclass(frozen=True)
class Options:
    """mcsplat against gsplat on one GPU."""

    training: Annotated[Training, tyro.conf.OmitArgPrefixes]
    arms: tuple[Literal["gsplat", "mcsplat", "mcsplat-graph"], ...] = ("gsplat", "mcsplat")
    """The arms to run, in this order."""
    steps: int = 5000
    """Training steps of each arm."""
    timed: int = 1000
    """The median is taken over the last N steps."""
    seed: int = 0
    """Seed of the initial model and of the view order."""
    dead_every: int = 1000
    """Steps between two dead_share figures."""
    out: Path | None = None
    """Results folder (default benchmarks/results/gpu_vs_gsplat)."""


# The table of results.md: one row per arm.
COLUMNS = [("arm", "arm", ""), ("Gaussians", "num_gaussians", ","), ("median ms/step", "median_step_ms", ".2f"),
           ("peak GPU MB", "peak_gpu_mb", ".0f"), ("PSNR", "psnr", ".2f"), ("SSIM", "ssim", ".4f"),
           ("train s", "train_seconds", ".1f")]


class Setup:
    """What both arms share: the configuration, the scene, the background and the view order."""

    def __init__(self, training: Training, steps: int, seed: int = 0, downscale: int = 1):
        self.config = TrainConfig(data=Path(training.data), steps=steps, cap_max=training.cap, device=training.device,
                                  seed=seed, downscale=downscale,
                                  model=ModelConfig(num_init_points=training.initial_points,
                                                    init=training.init_method))
        self.plan = Plan.literal(self.config)  # the paper's schedules, taken as they are
        self.device = torch.device(training.device)
        self.scene = load_scene(self.config.data, downscale=self.config.downscale)
        self.background = background_of(self.config, self.scene)
        self.radius = self.scene.radius

    def fresh(self):
        """The initial model and the generator both arms start from (identical for both)."""
        generator = torch.Generator(device=self.device).manual_seed(self.config.seed)
        model, _ = initial_model(self.config, self.scene, self.device, generator)
        return model, generator

    def views(self):
        sampler = ViewSampler(len(self.scene.train), self.config.seed)
        for _ in range(self.config.steps):
            yield self.scene.train[sampler.next()]


class McsplatArm:
    name = "mcsplat"

    def __init__(self, setup: Setup):
        self.setup = setup
        self.model, generator = setup.fresh()
        self.optimizers = make_optimizers(self.model, setup.config.optim, setup.radius)
        self.strategy = make_strategy(setup.config, setup.plan, setup.radius, generator)
        update = update_for(setup.device)  # the trainer's (on the CPU: the projection's backward fused with Adam)
        self.one_step = Step(self.model, self.optimizers, self.strategy, setup.config, setup.radius, setup.background,
                             setup.device, update=update)  # made once, as the trainer does

    def step(self, step: int, view) -> None:
        self.one_step(step, view, self.setup.plan)

    def count(self) -> int:
        return self.model.num_gaussians

    def opacities(self) -> torch.Tensor:
        return self.model.opacities.detach()

    @torch.no_grad()
    def render(self, view, sh_degree: int) -> torch.Tensor:
        return render(self.model, view.camera.to(self.setup.device), self.setup.background, sh_degree).rgb


class McsplatGraphArm(McsplatArm):
    name = "mcsplat-graph"

    def __init__(self, setup: Setup):
        super().__init__(setup)
        self.one_step = graphed(self.one_step, True)


class GsplatArm:
    name = "gsplat"
    KEYS = {"means": "means", "scales": "log_scales", "quats": "quats", "opacities": "opacity_logits",
            "sh0": "sh0", "shN": "shN"}  # gsplat's name -> mcsplat's (both keep log scales and logit opacities)

    def __init__(self, setup: Setup):
        from gsplat.strategy import MCMCStrategy

        self.setup = setup
        model, _ = setup.fresh()
        config = setup.config
        rates = config.optim.learning_rates(setup.radius)
        self.params = torch.nn.ParameterDict({k: torch.nn.Parameter(model.params[m].detach().clone())
                                              for k, m in self.KEYS.items()})
        self.optimizers = {k: torch.optim.Adam([self.params[k]], lr=rates[m], eps=config.optim.eps,
                                               betas=config.optim.betas, fused=True) for k, m in self.KEYS.items()}
        mc = config.mcmc
        self.strategy = MCMCStrategy(cap_max=mc.cap_max, noise_lr=mc.noise_lr, refine_start_iter=mc.refine_start,
                                     refine_stop_iter=mc.refine_stop, refine_every=mc.refine_every,
                                     min_opacity=mc.min_opacity)
        self.strategy.check_sanity(self.params, self.optimizers)
        self.state = self.strategy.initialize_state()
        self.bg = torch.tensor(setup.background, dtype=torch.float32, device=setup.device)

    def _rasterize(self, camera, sh_degree: int):
        from gsplat import rasterization

        p = self.params
        colors, alphas, info = rasterization(
            p["means"], p["quats"], torch.exp(p["scales"]), torch.sigmoid(p["opacities"]),
            torch.cat([p["sh0"], p["shN"]], 1), camera.world_to_camera[None].float(), camera.K[None].float(),
            camera.width, camera.height, sh_degree=sh_degree, backgrounds=self.bg[None], packed=False,
            near_plane=0.01, far_plane=1e10, eps2d=0.3, rasterize_mode="classic")
        return colors[0], info

    def step(self, step: int, view) -> None:
        s, config = self.setup, self.setup.config
        set_means_lr(self.optimizers, means_lr_at(step, config.steps, config.optim, s.radius))
        camera = view.camera.to(s.device)
        image, info = self._rasterize(camera, s.plan.sh_degree_at(step))
        mc = config.mcmc
        loss = (photometric_loss(image, view.image_float(s.device), config.ssim_weight)
                + mc.opacity_reg * torch.sigmoid(self.params["opacities"]).mean()
                + mc.scale_reg * torch.exp(self.params["scales"]).mean())
        loss.backward()
        loss.item()  # as mcsplat's step reads its loss (and checks it is finite)
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        self.strategy.step_post_backward(self.params, self.optimizers, self.state, step, info,
                                         lr=means_lr_at(step + 1, config.steps, config.optim, s.radius))

    def count(self) -> int:
        return len(self.params["means"])

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacities"].detach())

    @torch.no_grad()
    def render(self, view, sh_degree: int) -> torch.Tensor:
        return self._rasterize(view.camera.to(self.setup.device), sh_degree)[0]


def run_arm(arm_class, setup: Setup, timed: int, dead_every: int = 1000) -> dict:
    cuda = setup.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    arm = arm_class(setup)
    seconds = []
    dead_share = {}
    started = time.perf_counter()
    for step, view in enumerate(setup.views()):
        tick = C.now(setup.device)
        arm.step(step, view)
        seconds.append(C.now(setup.device) - tick)
        if (step + 1) % dead_every == 0:  # the next step refines: these are the Gaussians it will relocate
            dead = float((arm.opacities() <= setup.config.mcmc.min_opacity).float().mean())
            dead_share[str(step + 1)] = round(dead, 4)
            print(f"  {arm.name}: step {step + 1:,}, {arm.count():,} Gaussians ({100 * dead:.1f}% dead), "
                  f"{1000 * C.median(seconds[-200:]):.2f} ms/step lately", flush=True)
    total = time.perf_counter() - started
    peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else C.peak_rss_mb()
    degree = setup.plan.sh_degree_at(setup.config.steps - 1)
    scores = []
    for view in setup.scene.test:
        image = arm.render(view, degree).clamp(0, 1)
        target = view.image_float(setup.device)
        scores.append((psnr(image, target), ssim_metric(image, target)))
    return {"arm": arm.name, "steps": setup.config.steps, "cap": setup.config.cap_max,
            "num_gaussians": arm.count(), "median_step_ms": 1000 * C.median(seconds[-timed:]),
            "timed_steps": min(timed, len(seconds)), "train_seconds": round(total, 2), "peak_gpu_mb": round(peak, 1),
            "psnr": sum(s[0] for s in scores) / len(scores), "ssim": sum(s[1] for s in scores) / len(scores),
            "test_views": len(scores), "dead_share": dead_share}


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    training = args.training
    C.cuda_or_exit(training.device, "gpu_vs_gsplat")
    setup = Setup(training, args.steps, args.seed)
    out = C.results_dir("gpu_vs_gsplat", args.out)
    info = C.machine(training.device)
    print(C.machine_line(info), flush=True)
    records = []
    for name in args.arms:
        print(f"{name}: {args.steps:,} steps, cap {training.cap:,}, {training.initial_points:,} initial points",
              flush=True)
        arm = {"gsplat": GsplatArm, "mcsplat": McsplatArm, "mcsplat-graph": McsplatGraphArm}[name]
        record = run_arm(arm, setup, args.timed, args.dead_every)
        record.update(info)
        C.emit(record)
        records.append(record)
    by_arm = {r["arm"]: r for r in records}
    for name in ("mcsplat", "mcsplat-graph"):
        if name in by_arm and "gsplat" in by_arm:
            ratio = by_arm[name]["median_step_ms"] / by_arm["gsplat"]["median_step_ms"]
            print(f"step time {name} / gsplat: {ratio:.2f}x; PSNR {name} - gsplat: "
                  f"{by_arm[name]['psnr'] - by_arm['gsplat']['psnr']:+.2f} dB")
    C.write_results(out, records, C.markdown_table(records, COLUMNS) + "\n", show=True)


if __name__ == "__main__":
    main()
