"""Can the tile kernels (what CUDA runs), run on the CPU as cooperative fibers, serve the float64 checks that the
scalar compositing kernels serve today? (issue 60: if they could, the scalar compositing would be retired.)

Renders random scenes in float64 through both, forward and backward, and prints the median time of each and how far
their results differ. Run alone: `python benchmarks/float64_compositing.py` (a few seconds after the kernels are
compiled). docs/measurements-log.md has the figures and the decision.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mcsplat.render import Splats, render  # noqa: E402
from mcsplat.render.composite.function import set_cpu_kernels  # noqa: E402
from tests.render.test_render import make_camera, random_splats  # noqa: E402

SCENES = ((60, 45, 37), (2000, 160, 120))  # the tests' scenes, and a larger one
REPEATS = 5


def render_and_backward(kernels: str, splats: Splats, camera) -> tuple[float, torch.Tensor, torch.Tensor]:
    """(median seconds of a render and its backward through `kernels`, the colour, the means' gradient)."""
    set_cpu_kernels(kernels)
    times = []
    for _ in range(REPEATS + 1):  # the first is a warm-up
        leaves = Splats(*(getattr(splats, p).detach().clone().requires_grad_()
                          for p in ("means", "quats", "scales", "opacities", "sh")))
        tick = time.perf_counter()
        out = render(leaves, camera, (0.2, 0.5, 0.9))
        (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
        times.append(time.perf_counter() - tick)
    set_cpu_kernels("simd")
    return statistics.median(times[1:]), out.rgb.detach(), leaves.means.grad


def main() -> None:
    for count, width, height in SCENES:
        splats, camera = random_splats(count, 0, dtype=torch.float64), make_camera(width, height)
        scalar, rgb, grad = render_and_backward("scalar", splats, camera)
        tile, tile_rgb, tile_grad = render_and_backward("tile", splats, camera)
        print(f"{count} Gaussians at {width}x{height}, float64, render + backward: scalar {scalar * 1e3:.1f} ms, "
              f"tile on fibers {tile * 1e3:.1f} ms ({tile / scalar:.2f}x); colours differ by "
              f"{float((rgb - tile_rgb).abs().max()):.1e}, the means' gradients by "
              f"{float((grad - tile_grad).abs().max() / grad.abs().max()):.1e} of their largest")


if __name__ == "__main__":
    main()
