"""The binning stage: per tile, the Gaussians that reach it, front to back, with a mask of the 4x4 blocks each can
reach.

- warp_kernels.py: `TileBins` and `bin_gaussians`, Warp kernels around radix sorts (CUDA, and the CPU's second
  opinion), dispatching to the CPU's C++ loops.
- cpu_loops.py: the CPU's C++ loops over ranges of Gaussians, and its two sorts (C++ in cpu_loops_*.cpp).
- pair_room.py: the room of fixed size the Warp kernels list a training step's pairs in, so that no count is read.
- torch_oracle.py: the same lists in torch (the baseline render path's, and the tests' oracle).
"""
