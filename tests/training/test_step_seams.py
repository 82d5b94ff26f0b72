"""The two seams of a training step: a per-image learned module (per_image.py) plugs in through the Step's
`modules` alone, and a loss term (loss_terms.py) is one more entry in the list the step sums."""

from __future__ import annotations

import pytest
import torch

from mcsplat.appearance import Compensation, make_appearance
from mcsplat.config import TrainConfig
from mcsplat.data import load_scene
from mcsplat.errors import MCSplatError
from mcsplat.gaussians import GaussianModel
from mcsplat.loss_terms import StepContext, standard_terms
from mcsplat.optim import make_optimizers
from mcsplat.per_image import PerImageModule, PlanSteps
from mcsplat.planning import Plan
from mcsplat.pose_refinement import PoseRefinement
from mcsplat.run.scene import background_of
from mcsplat.run.state import TrainingState, ViewSampler
from mcsplat.strategy.mcmc import MCMCConfig, MCMCStrategy
from mcsplat.step import Step

CPU = torch.device("cpu")


class Brightness(PerImageModule):
    """A toy module: one learned brightness factor exp(b_i) per training image, pulled toward 1."""

    key = "brightness"

    def __init__(self, count: int, pull: float = 0.01):
        self.log_gain = torch.nn.Parameter(torch.zeros(count))
        self.optimizer = torch.optim.Adam([self.log_gain], lr=0.05)
        self.pull = pull

    def apply(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        return rgb * self.log_gain[index].exp()

    def regularization(self, index: int) -> torch.Tensor:
        return self.pull * self.log_gain[index] ** 2

    def step(self, step: int, plan: PlanSteps) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return {"log_gain": self.log_gain.detach().clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict | None) -> None:
        if state is None:
            raise MCSplatError("trained without brightness")
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"])
        self.optimizer.load_state_dict(state["optimizer"])


@pytest.fixture(scope="module")
def scene(mini_demo):
    return load_scene(mini_demo, downscale=4)  # 50x50 views: a step takes milliseconds


def _setup(scene):
    config = TrainConfig(data=scene.root, steps=100)
    model = GaussianModel.random_init(scene.radius, blender=True, num_points=500,
                                      generator=torch.Generator().manual_seed(0))
    optimizers = make_optimizers(model, Plan.literal(config).optim, scene.radius)
    strategy = MCMCStrategy(MCMCConfig(cap_max=500, refine_start=10**9), scene.radius,
                            torch.Generator().manual_seed(0))
    return config, model, optimizers, strategy


def _step(scene, step, model, optimizers, strategy, config, index, **seams):
    one_step = Step(model, optimizers, strategy, config, scene.radius, background_of(config, scene), CPU, **seams)
    return one_step(step, scene.train[index], Plan.literal(config), index)


def test_a_toy_per_image_module_trains_through_the_seam_and_its_state_round_trips(scene):
    config, model, optimizers, strategy = _setup(scene)
    brightness = Brightness(len(scene.train))
    for step in range(6):
        _step(scene, step, model, optimizers, strategy, config, step % 3, modules=[brightness])
    moved = brightness.log_gain.detach()
    assert moved[:3].abs().min() > 0, "each view stepped on learns its own factor"
    assert not moved[3:].any(), "a view never trained on keeps its own"

    # The run state saves it under its key, and a fresh module reads it back (Adam's moments too).
    state = TrainingState(model, optimizers, strategy, torch.Generator(), ViewSampler(len(scene.train), 0),
                          modules=[brightness])
    assert state.module("brightness") is brightness and state.module("poses") is None
    saved = state.checkpoint({}, [strategy.state_dict()])["brightness"]
    again = Brightness(len(scene.train))
    again.load_state_dict(saved)
    assert torch.equal(again.log_gain, brightness.log_gain)
    assert torch.equal(again.optimizer.state_dict()["state"][0]["exp_avg"],
                       brightness.optimizer.state_dict()["state"][0]["exp_avg"])
    with pytest.raises(MCSplatError):
        again.load_state_dict(None)


class GradientAtBackward:
    """StepPhases that copies the gradients of the model as the backward ends (before Adam clears them)."""

    def __init__(self, model: GaussianModel):
        self.model, self.grads = model, {}

    def rendered(self, result) -> None:
        pass

    def lap(self, phase: str) -> None:
        if phase == "backward":
            self.grads = {key: value.grad.clone() for key, value in self.model.params.items()}


def test_a_loss_term_added_to_the_list_adds_its_gradient(scene):
    grads, seen = [], []

    def opacity_push(ctx: StepContext) -> torch.Tensor:
        seen.append((ctx.view_index, ctx.rgb.shape, ctx.keep))
        return 0.5 * ctx.model.opacity_logits.sum()  # d/d(logit) = 0.5 for every Gaussian

    for extra in ([], [opacity_push]):
        config, model, optimizers, strategy = _setup(scene)
        phases = GradientAtBackward(model)
        terms = standard_terms(config.ssim_weight, strategy) + extra
        _step(scene, 0, model, optimizers, strategy, config, 2, loss_terms=terms, phases=phases)
        grads.append(phases.grads)
    without, with_term = grads
    torch.testing.assert_close(with_term["opacity_logits"] - without["opacity_logits"],
                               torch.full_like(without["opacity_logits"], 0.5), rtol=0, atol=1e-5)
    torch.testing.assert_close(with_term["means"], without["means"], rtol=0, atol=0)
    assert seen == [(2, (50, 50, 3), None)], "the term sees the step's view, its render and its (absent) mask"


def test_the_standard_terms_are_the_loss_the_step_sums_by_default(scene):
    """Passing the standard list is the same step as passing none: bit for bit."""
    losses = []
    for seams in ({}, {"loss_terms": None}, "standard"):
        config, model, optimizers, strategy = _setup(scene)
        if seams == "standard":
            seams = {"loss_terms": standard_terms(config.ssim_weight, strategy)}
        losses.append(_step(scene, 0, model, optimizers, strategy, config, 1, **seams).loss)
    assert losses[0] == losses[1] == losses[2]


def test_the_two_modules_of_the_options_keep_their_checkpoint_keys_and_refusals():
    transforms = make_appearance("affine", 4, CPU)
    appearance = Compensation(transforms, 0.003, 0.0003)
    poses = PoseRefinement(4, 1.0, CPU, lr=1e-3, weight_decay=0.0)
    assert (appearance.key, poses.key) == ("appearance", "poses")  # what checkpoints have always held
    saved = appearance.state_dict()
    del saved["mode"]  # a checkpoint from before the bilateral grid: affine
    appearance.load_state_dict(saved)
    with pytest.raises(MCSplatError, match="--appearance affine: the checkpoint was trained without it"):
        appearance.load_state_dict(None)
    with pytest.raises(MCSplatError, match="--pose-opt: the checkpoint was trained without it"):
        poses.load_state_dict(None)


class NormalsFacingTheCamera:
    """A toy surface term: pulls the normal map toward the camera (-z), so it reads an output render() gives only when
    asked."""

    render_outputs = frozenset({"normals"})

    def __init__(self):
        self.seen = []

    def __call__(self, ctx: StepContext) -> torch.Tensor:
        self.seen.append(ctx.result.normal is not None)
        return (ctx.result.normal[..., 2] + ctx.result.alpha).mean()


def test_a_term_that_reads_the_normal_map_gets_it_and_its_gradient(scene):
    grads = []
    term = NormalsFacingTheCamera()
    for extra in ([], [term]):
        config, model, optimizers, strategy = _setup(scene)
        phases = GradientAtBackward(model)
        seen = []
        terms = standard_terms(config.ssim_weight, strategy) + extra + [lambda ctx: seen.append(ctx.result.normal)]
        _step(scene, 0, model, optimizers, strategy, config, 1, loss_terms=terms, phases=phases)
        grads.append(phases.grads)
        assert (seen[0] is None) == (not extra), "the normal map is rendered only when a term asks for it"
    assert term.seen == [True]
    without, with_term = grads
    assert (with_term["quats"] - without["quats"]).abs().max() > 0, "the normals' gradient reaches the rotations"
