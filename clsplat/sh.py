"""The real spherical-harmonics basis on the torch side: gsplat's constants and sign convention.

This is the engine's own twin of ``sh_basis`` in ``kernels/common.h`` (same constants, same
order, degrees 0-4). Code that needs SH outside the kernels (rotating SH coefficients in the
model families, the float64 reference in :mod:`clsplat.reference`) imports it from here, so
production code never depends on the test oracle.
"""
from __future__ import annotations

import torch

__all__ = ["SH_C", "SH_C4", "MAX_SH_BASIS_DEGREE", "sh_basis"]

#: highest degree :func:`sh_basis` (and the kernels' ``sh_basis``) evaluates.
MAX_SH_BASIS_DEGREE = 4

SH_C = (0.2820947917738781, 0.48860251190292, 1.092548430592079, 0.3153915652525201,
        0.5462742152960395, 2.285228997322329, 0.4570457994644658, 1.445305721320277,
        1.865881662950577, 1.119528997770346, 0.5900435899266435, 0.9461746957575601)
# degree 4: the constants of gsplat's basis, in the order they appear below
SH_C4 = (0.6258357354491763, 1.770130769779931, 3.31161143515146, 0.47308734787878,
         4.683325804901025, 2.007139630671868, 1.984313483298443, 1.006230589874905)


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., 3] unit directions -> [..., (degree+1)^2] real SH basis (gsplat's convention).

    Differentiable, in the dtype of ``d``; ``degree`` in 0..4.
    """
    if not 0 <= degree <= MAX_SH_BASIS_DEGREE:
        raise ValueError(f"degree must be in 0..{MAX_SH_BASIS_DEGREE}, got {degree}")
    x, y, z = d.unbind(-1)
    b = [torch.full_like(x, SH_C[0])]
    if degree >= 1:
        b += [-SH_C[1] * y, SH_C[1] * z, -SH_C[1] * x]
    if degree >= 2:
        z2, c1, s1 = z * z, x * x - y * y, 2 * x * y
        b += [SH_C[4] * s1, -SH_C[2] * z * y, SH_C[11] * z2 - SH_C[3], -SH_C[2] * z * x, SH_C[4] * c1]
    if degree >= 3:
        t0 = -SH_C[5] * z2 + SH_C[6]
        t1 = SH_C[7] * z
        c2, s2 = x * c1 - y * s1, x * s1 + y * c1
        b += [-SH_C[10] * s2, t1 * s1, t0 * y, z * (SH_C[8] * z2 - SH_C[9]), t0 * x, t1 * c1, -SH_C[10] * c2]
    if degree >= 4:
        k = SH_C4
        c3, s3 = x * c2 - y * s2, x * s2 + y * c2
        t = z * (-k[4] * z2 + k[5])
        u = k[2] * z2 - k[3]
        w = -k[1] * z
        b += [k[0] * s3, w * s2, u * s1, t * y, k[6] * z * b[12] - k[7] * b[6], t * x, u * c1,
              w * c2, k[0] * c3]
    return torch.stack(b, -1)
