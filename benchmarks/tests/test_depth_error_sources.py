"""benchmarks/depth_error_sources.py's own compositing of each pixel's Gaussians (its alpha windows) is the
render's: the same accumulated alpha, and a window around 0.5 finds the render's median depth."""

from __future__ import annotations

import torch

import depth_error_sources
from tests.render.test_render import make_camera, random_splats


def test_the_window_loop_composites_as_the_render_does():
    splats = random_splats(400, seed=3, spread=0.8, log_scale=(-3.0, -1.5), opacity=(0.2, 0.99))
    camera = make_camera(width=50, height=40)
    narrow = (0.5 - 1e-9, 0.5 + 1e-9)
    out, maps, accumulated = depth_error_sources.window_depths(splats, camera, 3, windows=(narrow, (0.0, 1.0)))
    assert float(out.alpha.max()) > 0.9 and float((out.alpha > 0.5).double().mean()) > 0.3  # a case with medians
    assert torch.allclose(accumulated, out.alpha.double(), atol=1e-5)
    crossed = out.alpha > 0.5 + 1e-4
    assert torch.allclose(maps[narrow][crossed], out.median_depth.double()[crossed], atol=1e-4)
    # The whole ray's window is the alpha-weighted mean of the Gaussians' peak depths, within their depth range.
    covered = out.alpha > 0.01
    assert bool((maps[(0.0, 1.0)][covered] > 0).all())
