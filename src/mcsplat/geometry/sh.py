"""Real spherical harmonics up to degree 3, in the coefficient order and sign convention of 3DGS."""

from __future__ import annotations

import math

import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def degree_from_bases(num_bases: int) -> int:
    degree = math.isqrt(num_bases) - 1
    if num_bases != (degree + 1) ** 2 or not 0 <= degree <= 3:
        raise ValueError(f"SH coefficients must have 1, 4, 9 or 16 bases per channel, got {num_bases}")
    return degree


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient whose evaluated colour (+0.5) is `rgb`."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * SH_C0 + 0.5


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis values of all bands up to `degree` along unit directions [N, 3] -> [N, (degree+1)^2]."""
    basis = [torch.full_like(dirs[:, 0], SH_C0)]
    if degree >= 1:
        x, y, z = dirs.unbind(-1)
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                  SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                  SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    return torch.stack(basis, dim=-1)


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate SH of `degree` with coefficients [N, K, 3] (K >= (degree+1)^2) along unit directions [N, 3] -> [N, 3].

    One product of the basis with the coefficients: indexing the coefficients band by band would make autograd
    zero-fill a full-size gradient for every band.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    bases = num_sh_bases(degree)
    if coeffs.shape[-2] < bases:
        raise ValueError(f"SH degree {degree} needs {bases} coefficients, got {coeffs.shape[-2]}")
    return torch.einsum("nk,nkc->nc", sh_basis(degree, dirs), coeffs[:, :bases])
