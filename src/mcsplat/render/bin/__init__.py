"""The binning stage: per tile, the Gaussians that reach it, front to back, with a mask of the 4x4 blocks each can
reach.

- warp_kernels.py: `TileBins` and `bin_gaussians`, Warp kernels around radix sorts (CUDA, and the CPU's second
  opinion), dispatching to the CPU's C++ loops.
- cpu_loops.py: the CPU's C++ loops over ranges of Gaussians (C++ in cpu_loops.cpp).
- torch_oracle.py: the same lists in torch (the baseline render path's, and the tests' oracle).
"""
