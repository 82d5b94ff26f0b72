"""What is run: the scenes and settings of each scale, and the runs of every claim.

A run is named by what it varies (`cup-mcmc-random-no-gate`); runs shared by several claims are defined once (the
same-count ADC run is the reference of the initialisation claim's ADC row and of ADC with the regularizers; the
ablation reference, MCMC at the ablation cap, that of the noise and regulariser rows and of the initialisation
claim's MCMC row). The MCMC runs of the
same-count claim take ADC's final count as their cap (`cap="count:<ADC run>"`), as the paper's configs do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import _common as C


@dataclass(frozen=True)
class SceneSetting:
    name: str
    folder: str           # under the shared data folder
    downscale: int
    size: str             # the training image size this downscale gives, for the tables
    real: bool            # a real capture (SfM arms, the budget, init, noise and regulariser claims)
    test_stride: int = 1  # every N-th test view is scored
    fixed_cube: bool = False  # random init in the official [-1.3, 1.3]^3 cube whatever --model.init-extent says
                              # (object-centric scenes: NeRF-Synthetic, DTU normalised into the unit sphere)


@dataclass(frozen=True)
class Scale:
    name: str
    steps: int
    random_points: int                 # the paper's 100k random points, scaled with the pixels at CPU scale
    budget_caps: tuple[int, ...]       # the limited-budget claim's caps (the same-count cap is the last point)
    ablation_scenes: tuple[str, ...]   # the noise and regulariser ablations (the paper: T&T, Mip-NeRF 360)
    ablation_cap: int | None           # their cap, and MCMC's in the initialisation claim (None: ADC's count)
    scenes: dict[str, SceneSetting]
    close_db: float = 0.3              # pairs closer than this get extra seeds
    extra_seeds: tuple[int, ...] = (1, 2)

    @property
    def real_scenes(self) -> list[str]:
        return [name for name, s in self.scenes.items() if s.real]

    @property
    def extent_scenes(self) -> list[str]:
        """The real scenes whose random init follows --model.init-extent (the 1x / 3x claim)."""
        return [name for name in self.real_scenes if not self.scenes[name].fixed_cube]


def _scenes(downscales: dict[str, int], sizes: dict[str, str], lego_stride: int) -> dict[str, SceneSetting]:
    folders = {"lego": C.LEGO, "cup": "colmap_cup", "bird": "colmap_bird", "fern": "llff_fern/fern",
               "dtu": "dtu_scan24_monosdf/scan24"}
    return {name: SceneSetting(name, folder, downscales[name], sizes[name], real=name != "lego",
                               test_stride=lego_stride if name == "lego" else 1, fixed_cube=name in ("lego", "dtu"))
            for name, folder in folders.items()}


SCALES = {
    # 2 cores, a run of 1-3 minutes: images of 30-50k pixels, 2,000 steps with the paper's schedules fitted to them.
    # ADC's own count from random init is large at this scale (336k on the cup: scaled, its densification runs every
    # 7 steps), so the ablations and the initialisation claim's MCMC runs use a 30k cap, one Gaussian per pixel.
    "cpu": Scale("cpu", steps=2000, random_points=20_000, budget_caps=(1_000, 3_000), ablation_scenes=("cup", "bird"),
                 ablation_cap=30_000, scenes=_scenes({"lego": 2, "cup": 4, "bird": 4, "fern": 16, "dtu": 2},
                                {"lego": "200x200", "cup": "200x150", "bird": "136x240", "fern": "252x189",
                                 "dtu": "192x192"}, lego_stride=8)),
    # The paper's settings on a GPU: 30,000 steps, 100k random points, the shared images at their full size (lego
    # is shared at 400x400; the paper's is 800x800).
    "gpu": Scale("gpu", steps=30_000, random_points=100_000, budget_caps=(30_000, 100_000, 300_000),
                 ablation_scenes=("cup", "bird"), ablation_cap=None,
                 scenes=_scenes({"lego": 1, "cup": 1, "bird": 1, "fern": 8, "dtu": 1},
                                {"lego": "400x400", "cup": "800x600", "bird": "544x960", "fern": "504x378",
                                 "dtu": "384x384"}, lego_stride=1)),
}


@dataclass(frozen=True)
class Run:
    scene: str
    strategy: str                      # mcmc | adc
    init: str                          # random (the paper's cube) | sfm (the scene's points, else triangulated)
    variant: str = "default"           # what the run changes from the default, by name
    cap: int | str | None = None       # a number, "count:<run name>" (that run's final count) or None (ADC unbounded)
    options: tuple[tuple[str, Any], ...] = field(default=())  # dotted TrainConfig options: ("mcmc.noise_lr", 0.0)
    seed: int = 0

    @property
    def base_name(self) -> str:
        return f"{self.scene}-{self.strategy}-{self.init}" + ("" if self.variant == "default" else f"-{self.variant}")

    @property
    def name(self) -> str:
        return self.base_name + (f"-seed{self.seed}" if self.seed else "")

    def with_seed(self, seed: int) -> "Run":
        return Run(self.scene, self.strategy, self.init, self.variant, self.cap, self.options, seed)


# The rebuttal's noise designs and Table 3's noise row; the no-gate run at the paper's lambda diverges (the paper:
# "PSNR < 7"), so it also runs at the lambda_noise = 0.05 the paper trained it with.
NOISE_VARIANTS = {
    "no-noise": (("mcmc.noise_lr", 0.0),),
    "no-covariance": (("mcmc.noise_covariance", False),),
    "no-gate": (("mcmc.noise_gated", False), ("mcmc.noise_lr", 0.05)),
    "no-gate-paper-lambda": (("mcmc.noise_gated", False),),
    "all-params": (("mcmc.noise_all_params", True),),
    "linear-schedule": (("mcmc.noise_schedule", "linear"),),
    "neelakantan-schedule": (("mcmc.noise_schedule", "neelakantan"),),
}


@lru_cache(maxsize=None)  # the run list and the page ask for it many times
def noise_amount(schedule: str, steps: int) -> float:
    """How much noise a schedule gives over a run: the mean of its noise learning rate over the steps, over the
    start value (the same for every schedule). The paper's exponential decay gives 0.21."""
    from mcsplat.optim import OptimConfig
    from mcsplat.strategy.noise import noise_lr_at

    optim = OptimConfig()
    start = noise_lr_at("lr", 0, steps, optim, 1.0)
    return sum(noise_lr_at(schedule, step, steps, optim, 1.0) for step in range(steps)) / steps / start


def same_amount_variant(schedule: str, steps: int) -> tuple[str, tuple[tuple[str, Any], ...]]:
    """The paper's schedule with lambda_noise scaled so that it gives as much noise over the run as `schedule`: does
    a schedule's result come from its shape or from its amount?"""
    from mcsplat.strategy.mcmc import MCMCConfig

    ratio = noise_amount(schedule, steps) / noise_amount("lr", steps)
    return f"noise-as-much-as-{schedule}", (("mcmc.noise_lr", round(MCMCConfig().noise_lr * ratio, 1)),)


AMOUNT_SCHEDULES = ("linear", "neelakantan")  # the schedules compared with the paper's at the same amount
REGULARIZER_VARIANTS = {
    "no-opacity-reg": (("mcmc.opacity_reg", 0.0),),
    "no-scale-reg": (("mcmc.scale_reg", 0.0),),
    "no-regs": (("mcmc.opacity_reg", 0.0), ("mcmc.scale_reg", 0.0)),
}
ADC_WITH_REGULARIZERS = (("adc.opacity_reg", 0.01), ("adc.scale_reg", 0.01))
WEAK_OPACITY_REG = (("mcmc.opacity_reg", 0.001),)


def same_count_pair(scene: str, init: str) -> tuple[Run, Run]:
    adc = Run(scene, "adc", init)
    return adc, Run(scene, "mcmc", init, cap=f"count:{adc.name}")


def ablation_reference(scale: Scale, scene: str) -> Run:
    """The full method that the ablations and the 1x initialisation are compared with: MCMC from random init in
    3x the camera extent at the ablation cap (the same-count MCMC run where the scale has none)."""
    if scale.ablation_cap is None:
        return same_count_pair(scene, "random")[1]
    return Run(scene, "mcmc", "random", f"cap{C.human(scale.ablation_cap)}", scale.ablation_cap)


WIDE_START = (("model.init_scale", 1.0),)  # 3DGS's initial scale, 1.0 x the nearest-neighbour distance


def wide_start_run(scene: str, cap: int) -> Run:
    """MCMC at a budget cap starting from Gaussians as wide as ADC's (MCMC's own start at 0.1 x)."""
    return Run(scene, "mcmc", "sfm", f"cap{C.human(cap)}-init-scale-1", cap, WIDE_START)


TIGHT_CUBE = (("model.init_extent", 1.0),)
# In a cube of a third the size, the same number of random points lie a third as far apart, so MCMC's 0.1 x their
# spacing makes Gaussians a third as wide; 0.3 x gives them the width they have in the 3x cube.
TIGHT_CUBE_WIDE_START = TIGHT_CUBE + (("model.init_scale", 0.3),)


def tight_cube_wide_start_run(scale: Scale, scene: str) -> Run:
    """MCMC from random points in the 1x cube, its initial Gaussians as wide as those of the 3x cube."""
    return Run(scene, "mcmc", "random", "extent1x-init-scale-0.3", scale.ablation_cap, TIGHT_CUBE_WIDE_START)


def adc_at_regularized_count(scene: str) -> Run:
    """ADC without the regularizers, densification stopped at the final count of ADC with them: how much of what the
    regularizers cost ADC is the Gaussians they make it prune."""
    return Run(scene, "adc", "random", "with-regs-count", f"count:{scene}-adc-random-with-regs")


LONGER_STEPS = 3  # the longer runs of the random-against-SfM question train this many times the scale's steps


def random_against_sfm_runs(scale: Scale) -> list[Run]:
    """MCMC at the ablation cap on the first ablation scene from random and from SfM points, at the scale's steps
    and at LONGER_STEPS times as many: does the random init catch up when the run is longer, as the paper's 30,000
    steps let it?"""
    scene, cap = scale.ablation_scenes[0], scale.ablation_cap
    longer = (("steps", scale.steps * LONGER_STEPS),)
    name = f"cap{C.human(cap)}"
    longer_name = f"{name}-{LONGER_STEPS}x-steps"
    return [Run(scene, "mcmc", "sfm", name, cap), Run(scene, "mcmc", "random", longer_name, cap, longer),
            Run(scene, "mcmc", "sfm", longer_name, cap, longer)]


def runs(scale: Scale) -> list[Run]:
    """Every run of the scale at seed 0, in the order they are trained: first every claim on the first scenes (the
    same-count pairs of lego and the first two real captures, the ablations on the first ablation scene, the
    initialisation and budget runs on the first two real captures), then the same on the other scenes, so that a
    pass stopped early has covered every claim."""
    out: dict[str, Run] = {}
    for _, run in sorted(_every_run(scale), key=lambda pair: pair[0]):  # sorted() keeps the order within a priority
        out.setdefault(run.name, run)  # a run two claims share is trained where it first comes
    return list(out.values())


def _every_run(scale: Scale):
    first_real = scale.real_scenes[:2]
    for scene, setting in scale.scenes.items():                      # 1. same count as 3DGS
        for init in ("random", "sfm") if setting.real else ("random",):
            core = not setting.real or scene in first_real
            for run in same_count_pair(scene, init):
                yield (0 if core else 2.8 if init == "sfm" else 3), run
    for i, scene in enumerate(scale.ablation_scenes):                # 5. regularizers, 4. noise, 6. time
        priority, reference = (1 if i == 0 else 3), ablation_reference(scale, scene)
        yield priority, reference
        for name, opts in REGULARIZER_VARIANTS.items():
            yield priority, Run(scene, "mcmc", "random", name, reference.cap, opts)
        yield priority, Run(scene, "adc", "random", "with-regs", None, ADC_WITH_REGULARIZERS)
        yield max(priority, 2.78), adc_at_regularized_count(scene)   # 5. why: the count ADC keeps
        for name, opts in NOISE_VARIANTS.items():
            yield priority, Run(scene, "mcmc", "random", name, reference.cap, opts)
        if i == 0:                                                   # 4. why: the amount of noise
            for schedule in AMOUNT_SCHEDULES:
                name, opts = same_amount_variant(schedule, scale.steps)
                yield 2.79, Run(scene, "mcmc", "random", name, reference.cap, opts)
        sfm_cap = same_count_pair(scene, "sfm")[1].cap
        yield priority, Run(scene, "mcmc", "sfm", "opacity-reg-0.001", sfm_cap, WEAK_OPACITY_REG)
    for scene in scale.extent_scenes:                                # 3. initialisation in 1x the camera extent
        priority = 2 if scene in first_real else 3
        reference = ablation_reference(scale, scene)
        yield priority, reference
        yield priority, Run(scene, "adc", "random", "extent1x", None, TIGHT_CUBE)
        yield priority, Run(scene, "mcmc", "random", "extent1x", reference.cap, TIGHT_CUBE)
        if scene in first_real and scale.ablation_cap is not None:      # 3. why: the width of the start
            yield 2.77, tight_cube_wide_start_run(scale, scene)
    if scale.ablation_cap is not None:                               # 3. why random init lags at this scale
        for run in random_against_sfm_runs(scale):
            yield 2.7, run
    for scene in scale.real_scenes:                                  # 2. limited budget
        for cap in scale.budget_caps:
            for strategy in ("mcmc", "adc"):
                yield (2 if scene in first_real else 3), Run(scene, strategy, "sfm", f"cap{C.human(cap)}", cap)
    for scene in first_real:                                         # 2. why: MCMC with 3DGS's initial scale
        for cap in scale.budget_caps:
            yield 2.75, wide_start_run(scene, cap)


@dataclass(frozen=True)
class Comparison:
    """One row of a claim: `variant` against `baseline` on a scene (the sign the paper expects: + = variant ahead)."""

    claim: str
    label: str
    baseline: Run
    variant: Run


def comparisons(scale: Scale) -> list[Comparison]:
    rows = []
    for scene, setting in scale.scenes.items():
        for init in ("random", "sfm") if setting.real else ("random",):
            adc, mcmc = same_count_pair(scene, init)
            rows.append(Comparison("count", f"{scene}, {init} init", adc, mcmc))
    by_variant = {r.name: r for r in runs(scale)}
    for scene in scale.extent_scenes:
        for run in (same_count_pair(scene, "random")[0], ablation_reference(scale, scene)):
            rows.append(Comparison("init", f"{scene}, {run.strategy.upper()}: 1x against 3x",
                                   run, by_variant[f"{scene}-{run.strategy}-random-extent1x"]))
    for scene in [s for s in scale.extent_scenes if s in scale.real_scenes[:2] and scale.ablation_cap is not None]:
        rows.append(Comparison("init-start", scene, ablation_reference(scale, scene),
                               tight_cube_wide_start_run(scale, scene)))
    if scale.ablation_cap is not None:
        sfm, random_longer, sfm_longer = random_against_sfm_runs(scale)
        rows.append(Comparison("init-steps", f"{scale.steps:,} steps", sfm, ablation_reference(scale, sfm.scene)))
        rows.append(Comparison("init-steps", f"{scale.steps * LONGER_STEPS:,} steps", sfm_longer, random_longer))
    for scene in scale.ablation_scenes:
        mcmc = ablation_reference(scale, scene)
        for name in NOISE_VARIANTS:
            rows.append(Comparison("noise", f"{scene}, {name}", mcmc, by_variant[f"{scene}-mcmc-random-{name}"]))
        for schedule in AMOUNT_SCHEDULES if scene == scale.ablation_scenes[0] else ():
            name = same_amount_variant(schedule, scale.steps)[0]
            rows.append(Comparison("noise-amount", schedule, by_variant[f"{scene}-mcmc-random-{schedule}-schedule"],
                                   by_variant[f"{scene}-mcmc-random-{name}"]))
        for name in REGULARIZER_VARIANTS:
            rows.append(Comparison("regularizers", f"{scene}, {name}", mcmc,
                                   by_variant[f"{scene}-mcmc-random-{name}"]))
        adc = same_count_pair(scene, "random")[0]
        rows.append(Comparison("regularizers", f"{scene}, ADC with the MCMC regularizers", adc,
                               by_variant[f"{adc.base_name}-with-regs"]))
        rows.append(Comparison("regularizers-count", scene, adc, adc_at_regularized_count(scene)))
    for scene in scale.ablation_scenes:
        mcmc = same_count_pair(scene, "sfm")[1]
        rows.append(Comparison("time", f"{scene}, opacity reg 0.001 against 0.01", mcmc,
                               by_variant[f"{mcmc.base_name}-opacity-reg-0.001"]))
    for scene in scale.real_scenes:
        for cap in scale.budget_caps:
            adc = by_variant[f"{scene}-adc-sfm-cap{C.human(cap)}"]
            mcmc = by_variant[f"{scene}-mcmc-sfm-cap{C.human(cap)}"]
            rows.append(Comparison("budget", f"{scene}, cap {C.human(cap)}", adc, mcmc))
            if scene in scale.real_scenes[:2]:
                rows.append(Comparison("budget-start", f"{scene}, cap {C.human(cap)}", mcmc,
                                       wide_start_run(scene, cap)))
    return rows
