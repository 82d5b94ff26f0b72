"""The SSIM of 3DGS, fused with its gradient: warp.py holds the window and constants and the Warp kernels (CUDA
first), cpu.py the SIMD C++ kernels that train on the CPU; losses.py chooses between them."""
