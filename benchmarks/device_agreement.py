"""Does a CUDA training step compute what the CPU's computes? One trained run's model, a few of its training views:
the image, the loss and every parameter's gradient from each path, side by side.

    python benchmarks/device_agreement.py RUN [RUN ...] [--views 3] [--paths cuda-tile cuda-scalar cpu]

A path is a device and its compositing kernels: cuda-tile (what CUDA trains with), cuda-scalar (the per-pixel
kernels on CUDA) and cpu (the SIMD kernels, the path whose runs come out right). The loss is the step's own:
(1 - 0.2) L1 + 0.2 (1 - SSIM) plus the MCMC paper's L1 terms on opacity and scale, at the run's last SH degree and
full resolution. The last path named is the reference: each other path's record gives, per parameter, the relative
L2 error of its gradient and the share of Gaussians that have a gradient on one path and none on the other (a
Gaussian the rasterizer drops on one device gets no gradient there, and MCMC's opacity term then fades it out).
Float32 atomics make a few 1e-6 of relative error normal; a path that disagrees by 1e-2 or more, or drops
Gaussians, has a defect.

One JSON line per (run, view, path) and a summary line per run; a run without CUDA compares the CPU path with itself
(the dry run of gpu_session.py).
"""

from __future__ import annotations

import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import torch
import tyro

import _common as C
from mcsplat import losses, render
from mcsplat.render.composite.function import cuda_kernels, set_cuda_kernels
from mcsplat.run.trained import load
from mcsplat.strategy.base import l1_regularizers

KernelPath = Literal["cuda-tile", "cuda-scalar", "cpu"]
PATHS: tuple[KernelPath, ...] = typing.get_args(KernelPath)
OPACITY_REG = SCALE_REG = 0.01  # the MCMC defaults (strategy/mcmc.py)


@dataclass(frozen=True)
class Options:
    """A training step on CUDA against the CPU's, on trained runs' models."""

    runs: Annotated[tuple[Path, ...], tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
    """Trained run folders."""
    views: int = 3
    """Training views compared, spread over the list."""
    paths: tuple[KernelPath, ...] = PATHS
    """The paths compared; the last one is the reference."""


def step_gradients(run, view, path: str) -> dict:
    """The image, the loss and the gradient of every parameter of the run's model for `view` on `path`."""
    device = torch.device("cpu" if path == "cpu" else "cuda")
    if device.type == "cuda":
        set_cuda_kernels(path.removeprefix("cuda-"))
    model = run.model.to(device)
    model.zero_grad(set_to_none=True)
    camera = view.camera.to(device)
    target = view.image_float(device)
    result = render.render(model, camera, run.background, run.sh_degree)
    loss = losses.photometric_loss(result.rgb, target) + l1_regularizers(model, OPACITY_REG, SCALE_REG)
    loss.backward()
    grads = {name: (p.grad.detach().double().cpu() if p.grad is not None else torch.zeros(p.shape, dtype=torch.float64))
             for name, p in model.named_parameters()}
    return {"image": result.rgb.detach().double().cpu(), "loss": loss.item(), "pairs": result.num_pairs,
            "grads": grads}


def compare(found: dict, reference: dict) -> dict:
    """How far `found` is from `reference`: the image, the loss, and each gradient (relative L2 error, and the
    share of Gaussians with a gradient on exactly one of the two)."""
    record = {"image_max_abs": float((found["image"] - reference["image"]).abs().max()),
              "loss": found["loss"], "loss_reference": reference["loss"], "pairs": found["pairs"],
              "pairs_reference": reference["pairs"]}
    for name, grad in found["grads"].items():
        other = reference["grads"][name]
        error = float((grad - other).norm() / other.norm().clamp(min=1e-30))
        has, has_other = (grad.reshape(grad.shape[0], -1) != 0).any(1), (other.reshape(other.shape[0], -1) != 0).any(1)
        record[name] = {"relative_error": error, "only_here": float((has & ~has_other).double().mean()),
                        "only_reference": float((~has & has_other).double().mean())}
    return record


def main() -> None:
    args = tyro.cli(Options, description=__doc__)
    if not args.runs:
        sys.exit("device_agreement: give one or more trained run folders")
    paths = args.paths if torch.cuda.is_available() else ("cpu", "cpu")
    chosen = cuda_kernels()
    for run_path in args.runs:
        run = load(run_path, torch.device("cpu"))
        views = run.scene.train[::max(1, len(run.scene.train) // args.views)][:args.views]
        worst: dict[str, float] = {}
        for view in views:
            reference = step_gradients(run, view, paths[-1])
            for path in paths[:-1]:
                record = compare(step_gradients(run, view, path), reference)
                C.emit({"run": str(run_path), "view": view.name, "path": path, "reference": paths[-1],
                        "gaussians": run.model.num_gaussians, **record})
                errors = [v["relative_error"] for v in record.values() if isinstance(v, dict)]
                worst[path] = max(worst.get(path, 0.0), *errors)
        C.emit({"run": str(run_path), "summary": True, "step": run.step, "worst_relative_error": worst})
    set_cuda_kernels(chosen)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
