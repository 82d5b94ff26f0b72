"""How CPU work is cut across threads: small work stays on fewer of them (the pool's hand-off costs more than it
saves), unless the tests ask every thread to take a share of it."""

from __future__ import annotations

import torch

from mcsplat.compute.runtime import MIN_TILES_PER_WORKER, num_workers_for, set_cpu_threads
from mcsplat.ssim import cpu as ssim_cpu

CPU = torch.device("cpu")


def test_small_work_stays_on_one_thread_unless_split():
    try:
        set_cpu_threads(2)
        assert num_workers_for(CPU, 25) == 1, "a 67x67 image's 25 tiles: one thread"
        assert num_workers_for(CPU, 2 * MIN_TILES_PER_WORKER) == 2
        assert num_workers_for(torch.device("cuda"), 10_000) == 1, "one launch on CUDA"
        assert ssim_cpu._parts(67) == 1 and ssim_cpu._parts(2 * ssim_cpu.ROWS_PER_THREAD) == 2
        set_cpu_threads(2, split_small_work=True)
        assert num_workers_for(CPU, 25) == 2 and num_workers_for(CPU, 1) == 1
        assert ssim_cpu._parts(67) == 2 and ssim_cpu._parts(ssim_cpu.ROWS_PER_PART - 1) == 1
    finally:
        set_cpu_threads(None)
