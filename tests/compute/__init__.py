"""compute/: the C++ of the CPU kernels and the CPU they are built for."""
