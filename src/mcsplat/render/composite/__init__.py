"""The compositing stage: rgb, alpha, expected depth and which Gaussians contributed, with a hand-written backward.

- function.py: the autograd Function, dispatching to the kernels kernel_choice.py chooses.
- cpu_simd.py: the CPU's SIMD kernels (a 4x4 pixel block per 16-lane vector; C++ in cpu_simd_*.cpp) and their host
  side.
- warp_tiles.py: CUDA's tile kernels (a block of threads per tile; on the CPU as cooperative fibers for the tests).
- warp_scalar.py: the scalar Warp kernels (a thread per pixel: float64 on the CPU, the baseline).
- warp_pixel.py: the Warp functions both kernel families call per pixel (alpha, outputs, the backward's walk).
"""
