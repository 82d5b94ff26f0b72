"""Kernels that only the CPU gets (SIMD compositing); render/launch.py chooses them for float32 tensors on the CPU."""
