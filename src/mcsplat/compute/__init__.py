"""The Warp runtime every kernel of mcsplat goes through: initialisation, the CPU thread pool and launchers, the
torch <-> Warp views, and compiling kernel modules ahead of their first launch.

It knows nothing of Gaussians or images: the renderer, the fused SSIM and the geometry kernels sit on top of it.
"""
