"""Real spherical harmonics up to degree 3, with the constants and sign conventions of 3DGS.

Colour of a Gaussian seen along unit direction d (from the camera centre to the Gaussian's mean):
``rgb = max(0, sum_k Y_k(d) * sh_k + 0.5)``, which is what 3DGS training code and viewers assume
for the coefficients stored in PLY files.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..gaussians.container import SH_C0, sh_degree_from_bases

SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(
    dirs: Tensor,  # [N, 3] unit view directions
    degree: int,
) -> Tensor:  # [N, (degree + 1)^2]
    """The real SH basis functions Y_k(d), k = 0 .. (degree + 1)^2 - 1, in the 3DGS order."""
    if not 0 <= degree <= 3:
        raise ValueError(f"degree: expected 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * x * y * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(basis, -1)


def sh_to_rgb(
    sh: Tensor,  # [N, K, 3] coefficients, K = (degree + 1)^2, DC first
    dirs: Tensor,  # [N, 3] view directions (need not be unit length)
) -> Tensor:  # [N, 3]
    """View-dependent colour, ``max(0, SH(d) + 0.5)`` (not clamped above: the image is clamped)."""
    degree = sh_degree_from_bases(sh.shape[1])
    if degree == 0:
        return (SH_C0 * sh[:, 0] + 0.5).clamp_min(0.0)
    # A zero direction (mean at the camera centre) has no view dependence: its basis is DC only.
    unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(math.ulp(1.0))
    return (torch.einsum("nk,nkc->nc", sh_basis(unit, degree), sh) + 0.5).clamp_min(0.0)
