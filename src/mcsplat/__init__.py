"""mcsplat: 3D Gaussian Splatting trained with the MCMC method of Kheradmand et al. (NeurIPS 2024)."""

__version__ = "0.1.0"
