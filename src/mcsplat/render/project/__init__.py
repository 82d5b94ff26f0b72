"""The projection stage: each Gaussian's screen-space mean, conic, depth, radius and tiles, and its SH colour.

- torch_autograd.py: in torch, autograd giving the backward (the readable version, the baseline render path's);
  `Projection`, what every version returns.
- warp_kernel.py: one Warp kernel with a hand-written backward (CUDA, float64, the CPU's second opinion), and the
  autograd Function that dispatches to it or to the CPU's SIMD kernels, as kernel_choice.py says.
- cpu_simd.py: the CPU's SIMD kernels (16 Gaussians per vector; C++ in cpu_simd_*.cpp) and their host side.
"""
