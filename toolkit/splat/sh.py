"""Real spherical harmonics up to degree 3, in the basis and sign convention of 3DGS/gsplat.

A colour is ``sum_k basis_k(dir) * coeff_k + 0.5``, clamped at 0; ``dir`` points from the
camera centre to the Gaussian. Keeping gsplat's convention means a PLY trained here looks
the same in any 3DGS viewer and the CUDA backend renders identical colours.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Coefficients per channel for SH ``degree`` (1, 4, 9, 16)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    return (degree + 1) ** 2


def degree_from_bases(k: int) -> int:
    """Inverse of ``num_sh_bases``; raises for counts that are not a square up to 16."""
    for d in range(4):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for d in 0..3")


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """[M, (degree+1)^2] basis values for unit directions ``dirs`` [M, 3]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree > 0:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            C2[0] * xy,
            C2[1] * yz,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * xz,
            C2[4] * (xx - yy),
        ]
        if degree > 2:
            out += [
                C3[0] * y * (3.0 * xx - yy),
                C3[1] * xy * z,
                C3[2] * y * (4.0 * zz - xx - yy),
                C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
                C3[4] * x * (4.0 * zz - xx - yy),
                C3[5] * z * (xx - yy),
                C3[6] * x * (xx - 3.0 * yy),
            ]
    return torch.stack(out, -1)


def eval_sh(coeffs: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """[M, 3] colours from coefficients [M, K, 3] (K >= (degree+1)^2) and directions [M, 3].

    ``dirs`` need not be normalised. Only the first (degree+1)^2 coefficients are used, which
    is how training raises the degree: higher bands exist from the start but stay unused.
    """
    k = num_sh_bases(degree)
    if coeffs.shape[1] < k:
        raise ValueError(f"degree {degree} needs {k} SH coefficients, model has {coeffs.shape[1]}")
    if degree == 0:
        rgb = C0 * coeffs[:, 0]
    else:
        d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        basis = sh_basis(d, degree)  # [M, k]
        # Broadcast-multiply and sum: a batched [1, k] x [k, 3] matmul per Gaussian (what
        # einsum turns this into) is several times slower on CPU.
        rgb = (basis[:, :, None] * coeffs[:, :k]).sum(1)
    return torch.clamp_min(rgb + 0.5, 0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient that renders ``rgb`` (0..1) when the other bands are zero."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * C0 + 0.5
