"""The geometry of one Gaussian, shared by the model, the renderer and the strategies: quaternion rotations, the
3D covariance (in torch, and as a Warp kernel applied to vectors) and the real spherical harmonics of 3DGS."""
