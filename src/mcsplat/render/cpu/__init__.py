"""Kernels that only the CPU gets (SIMD projection and compositing, the binning's C++ loops); render/kernel_choice.py
chooses them for float32 tensors on the CPU."""
