"""mcsplat: 3D Gaussian Splatting trained with the MCMC method of Kheradmand et al. (NeurIPS 2024)."""

import os

# OpenMP threads that spin after each torch op steal the cores the rasterizer's own threads need (a render +
# backward is markedly slower with them spinning: docs/measurements-log.md, "CPU kernels (rasterizer.py,
# train_speed.py), 2026-11-22"); let them sleep. Only effective when mcsplat is imported before torch loads (the CLI,
# the benchmarks and the tests do so).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
