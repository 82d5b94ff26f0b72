"""`--appearance bilateral-grid`: a bilateral grid of affine colour transforms per training image.

The affine transform of `--appearance affine` takes one colour change for a whole photo; a phone's exposure and tone
curve also depend on where a pixel is and how bright it is (vignetting, local tone mapping, a curve bent in the
shadows). Following gsplat's bilateral grids (after Wang et al., "Bilateral Guided Radiance Field Processing"), each
training image gets a 16 x 16 x 8 grid of 3x4 affine transforms over image columns, rows and brightness, sliced at
every pixel (slicing.py). Each grid starts at the identity everywhere. Its regulariser is the total variation of the
grid (the transform changes smoothly across the image and the brightness levels) plus the affine mode's pull toward
identity, here on the grid's mean transform. As for the affine mode, the transforms are held at a median of identity
(cell by cell), so that a change every photo shares is learned by the scene, not by the grids.
"""

from __future__ import annotations

import torch


GRID_SHAPE = (16, 16, 8)  # columns, rows, brightness levels (gsplat's default)
CENTRE_EVERY = 10  # steps between two centrings (the median over the images' grids takes tens of ms)
# Per cell of one image's grid: 12 float32 numbers, held three times (the grid, RowAdam's first moment, and the
# working copy the median of a centring takes).
BYTES_PER_CELL = 12 * 4 * 3


def grids_bytes(count: int, shape: tuple[int, int, int]) -> int:
    """The memory the grids of `count` images of `shape` (columns, rows, levels) take while training."""
    columns, rows, levels = shape
    return count * columns * rows * levels * BYTES_PER_CELL


def _identity(levels: int, rows: int, columns: int, device) -> torch.Tensor:
    """[12, L, H', W'] holding [I | 0] in every cell."""
    affine = torch.eye(3, 4, device=device).reshape(12, 1, 1, 1)
    return affine.expand(12, levels, rows, columns).clone()


def total_variation(grid: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring cells of grid [12, L, H', W'], summed over its three axes."""
    return sum(grid.diff(dim=axis).pow(2).mean() for axis in (1, 2, 3))


class RowAdam:
    """Adam over one row of `rows` [N, G] per step: the row of the image the step trained on, the others untouched
    (their moments too, as torch's SparseAdam does; each row keeps its own step count for the bias correction). The
    second moment is one number per row (the mean over its entries): a cell that few pixels reach then moves in
    proportion to its gradient rather than by a full learning rate. (Per-entry moments, as plain Adam keeps them,
    scored level with this on the vignette test of tests/appearance/test_bilateral_grid.py: docs/imperfect-captures.md,
    "Exposure compensation".)"""

    def __init__(self, rows: torch.Tensor, lr: float, betas=(0.9, 0.999), eps: float = 1e-15):
        self.rows, self.betas, self.eps = rows, betas, eps
        self.param_groups = [{"lr": lr}]
        self.exp_avg = torch.zeros_like(rows)
        self.exp_avg_sq = torch.zeros_like(rows[:, :1])
        self.steps = torch.zeros(rows.shape[0], dtype=torch.int64)

    @torch.no_grad()
    def step_row(self, index: int, grad: torch.Tensor) -> None:
        beta1, beta2 = self.betas
        self.steps[index] += 1
        t = int(self.steps[index])
        self.exp_avg[index].mul_(beta1).add_(grad, alpha=1 - beta1)
        self.exp_avg_sq[index].mul_(beta2).add_(grad.square().mean(dim=0, keepdim=True), alpha=1 - beta2)
        denominator = (self.exp_avg_sq[index] / (1 - beta2 ** t)).sqrt().add_(self.eps)
        step_size = self.param_groups[0]["lr"] / (1 - beta1 ** t)
        self.rows[index].addcdiv_(self.exp_avg[index], denominator, value=-step_size)

    def state_dict(self) -> dict:
        return {"exp_avg": self.exp_avg, "exp_avg_sq": self.exp_avg_sq, "steps": self.steps,
                "lr": self.param_groups[0]["lr"]}

    def load_state_dict(self, state: dict) -> None:
        self.exp_avg.copy_(state["exp_avg"])
        self.exp_avg_sq.copy_(state["exp_avg_sq"])
        self.steps.copy_(state["steps"])
        self.param_groups[0]["lr"] = state["lr"]


class _GridOptimizer:
    """The optimizer interface the trainer's Compensation drives: step() applies RowAdam to the grid of the image
    this step read (BilateralGridAppearance keeps it as a leaf tensor while the step runs)."""

    def __init__(self, owner: "BilateralGridAppearance", adam: RowAdam):
        self.owner, self.adam = owner, adam
        self.param_groups = adam.param_groups

    def step(self) -> None:
        current = self.owner.current
        if current is not None and current[1].grad is not None:
            self.adam.step_row(current[0], current[1].grad.reshape(-1))

    def zero_grad(self, set_to_none: bool = True) -> None:
        self.owner.current = None

    def state_dict(self) -> dict:
        return self.adam.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.adam.load_state_dict(state)


class BilateralGridAppearance(torch.nn.Module):
    """`grids` [N, 12 L H' W']: one bilateral grid per training image (flattened), the identity at start.

    A step reads one image's grid: it is taken out as a leaf tensor (`current`) for the render's slicing and the
    regulariser, and its gradient steps that row alone (RowAdam: torch's SparseAdam, which visits every image's grid,
    added a sizeable fixed time to every step, whatever the image size; docs/imperfect-captures.md, "Exposure
    compensation")."""

    MODE = "bilateral-grid"  # the --appearance value (checkpoints record it)

    def __init__(self, count: int, device: torch.device | str = "cpu", pull_weight: float = 0.01,
                 tv_weight: float = 10.0, shape: tuple[int, int, int] = GRID_SHAPE):
        super().__init__()
        columns, rows, levels = shape
        self.shape = (12, levels, rows, columns)
        self.pull_weight, self.tv_weight = pull_weight, tv_weight
        self.register_buffer("identity", _identity(levels, rows, columns, device).reshape(1, -1), persistent=False)
        self.grids = torch.nn.Parameter(self.identity.repeat(count, 1), requires_grad=False)
        self.current: tuple[int, torch.Tensor] | None = None  # (image, its grid as a leaf) during a training step

    def grid(self, index: int) -> torch.Tensor:
        """Image `index`'s grid [12, L, H', W'], the same leaf tensor for every use within a step."""
        if self.current is None or self.current[0] != index:
            self.current = (index, self.grids[index].detach().view(self.shape).requires_grad_())
        return self.current[1]

    def forward(self, index: int, rgb: torch.Tensor) -> torch.Tensor:
        """rgb [H, W, 3] as image `index`'s camera recorded it."""
        from .slicing import slice_grid  # Warp loads with the first slice: the CLI imports this package to start

        return slice_grid(self.grid(index), rgb)

    def optimizer(self, lr: float) -> _GridOptimizer:
        return _GridOptimizer(self, RowAdam(self.grids.data, lr))

    @torch.no_grad()
    def centre(self, step: int) -> None:
        """Hold the cell-by-cell median of the grids at the identity (see AffineAppearance.centre for why the
        median). Every CENTRE_EVERY steps: the median over the images is the costliest part of this mode."""
        if step % CENTRE_EVERY == 0:
            self.grids -= self.grids.median(dim=0, keepdim=True).values - self.identity

    def penalty(self, index: int) -> torch.Tensor:
        grid = self.grid(index)
        mean_transform = grid.mean(dim=(1, 2, 3))
        pull = (mean_transform - self.identity.view(self.shape)[:, 0, 0, 0]).pow(2).sum()
        return self.tv_weight * total_variation(grid) + self.pull_weight * pull
