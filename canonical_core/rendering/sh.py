"""Real spherical harmonics up to degree 3, with the constants and sign conventions of 3DGS.

Colour of a Gaussian seen along unit direction d (from the camera centre to the Gaussian's mean):
``rgb = max(0, sum_k Y_k(d) * sh_k + 0.5)``, which is what 3DGS training code and viewers assume
for the coefficients stored in PLY files.

`sh_basis` and `sh_to_rgb` are the PyTorch definitions (differentiable); `sh_basis_at_points` and
`sh_to_rgb_fast` are their numba fast paths (float32, no autograd), held to them by tests.
"""

from __future__ import annotations

import math

import numba
import numpy as np
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


@numba.njit(parallel=True, cache=True)
def _sh_basis_kernel(points, centre, degree, c0, c1, c2, c3, out):
    # sh_basis with the view direction (centre -> point) fused in, so no [N, 3] temporary is made.
    for i in numba.prange(points.shape[0]):
        x = points[i, 0] - centre[0]
        y = points[i, 1] - centre[1]
        z = points[i, 2] - centre[2]
        n = np.sqrt(x * x + y * y + z * z)
        if n > 0:
            x, y, z = x / n, y / n, z / n
        b = out[i]
        b[0] = c0
        if degree >= 1:
            b[1], b[2], b[3] = -c1 * y, c1 * z, -c1 * x
        if degree >= 2:
            xx, yy, zz = x * x, y * y, z * z
            b[4], b[5], b[6] = c2[0] * x * y, c2[1] * y * z, c2[2] * (2 * zz - xx - yy)
            b[7], b[8] = c2[3] * x * z, c2[4] * (xx - yy)
            if degree >= 3:
                b[9], b[10] = c3[0] * y * (3 * xx - yy), c3[1] * x * y * z
                b[11], b[12] = c3[2] * y * (4 * zz - xx - yy), c3[3] * z * (2 * zz - 3 * xx - 3 * yy)
                b[13], b[14], b[15] = c3[4] * x * (4 * zz - xx - yy), c3[5] * z * (xx - yy), c3[6] * x * (xx - 3 * yy)


def sh_basis_at_points(
    points: np.ndarray,  # [N, 3] float32
    centre: np.ndarray,  # [3] float32 viewpoint
    degree: int,
) -> np.ndarray:  # [N, (degree + 1)^2] float32
    """Fast path of ``sh_basis`` for the directions from ``centre`` to ``points`` (zero direction: DC only)."""
    if not 0 <= degree <= 3:
        raise ValueError(f"degree: expected 0..3, got {degree}")
    out = np.empty((points.shape[0], (degree + 1) ** 2), np.float32)
    _sh_basis_kernel(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(centre, np.float32), degree,
                     np.float32(SH_C0), np.float32(SH_C1), np.array(SH_C2, np.float32), np.array(SH_C3, np.float32), out)  # fmt: skip
    return out


@numba.njit(parallel=True, cache=True)
def _sh_contract_kernel(basis, sh, out):
    for i in numba.prange(sh.shape[0]):
        for c in range(3):
            total = np.float32(0.0)
            for k in range(sh.shape[1]):
                total += basis[i, k] * sh[i, k, c]
            out[i, c] = max(np.float32(0.0), total + np.float32(0.5))


_SH1_CHUNK = 512  # Gaussians per parallel task of `_sh1_colour_kernel`


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _sh1_colour_kernel(points, centre, sh, c0, c1, out):
    # Degree 1 (the default): `_sh_basis_kernel` and `_sh_contract_kernel` in one pass, the same
    # operations in the same order, so the same bits. Per chunk, a branch-free first loop (flat
    # inputs at 3 i + k and 12 i + k, scratch rows at constant offsets, IEEE division: a zero
    # direction divides by 1 and stays zero) compiles to vector code; `out` may be strided, so a
    # second function copies into it.
    p, h = points.reshape(-1), sh.reshape(-1)
    cx, cy, cz = centre
    n = points.shape[0]
    for chunk in numba.prange((n + _SH1_CHUNK - 1) // _SH1_CHUNK):
        first, count = chunk * _SH1_CHUNK, min(_SH1_CHUNK, n - chunk * _SH1_CHUNK)
        rgb = np.empty(3 * _SH1_CHUNK, np.float32)
        for j in range(count):
            i = first + j
            x, y, z = p[3 * i] - cx, p[3 * i + 1] - cy, p[3 * i + 2] - cz
            norm = np.sqrt(x * x + y * y + z * z)
            d = norm if norm > 0 else np.float32(1.0)
            x, y, z = x / d, y / d, z / d
            b1, b2, b3 = -c1 * y, c1 * z, -c1 * x
            for c in range(3):
                total = np.float32(0.0) + c0 * h[12 * i + c]
                total += b1 * h[12 * i + 3 + c]
                total += b2 * h[12 * i + 6 + c]
                total += b3 * h[12 * i + 9 + c]
                rgb[c * _SH1_CHUNK + j] = max(np.float32(0.0), total + np.float32(0.5))
        _copy_rgb(rgb, first, count, out)


@numba.njit(cache=True)
def _copy_rgb(rgb, first, count, out):
    for j in range(count):
        out[first + j, 0], out[first + j, 1], out[first + j, 2] = rgb[j], rgb[_SH1_CHUNK + j], rgb[2 * _SH1_CHUNK + j]


def sh_to_rgb_fast(
    sh: Tensor,  # [N, K, 3] coefficients, K = (degree + 1)^2, DC first
    dirs: Tensor,  # [N, 3] view directions (need not be unit length), or points seen from ``centre``
    centre: np.ndarray | None = None,  # [3] viewpoint: the directions are dirs - centre (None: dirs as given)
    out: np.ndarray | None = None,  # [N, 3] float32 to write into (rows may be strided); None: a new array
) -> Tensor:  # [N, 3] float32 on the CPU (a view of ``out`` when given)
    """Fast path of ``sh_to_rgb`` (numba, float32, no autograd): one pass over the
    Gaussians instead of about twenty tensor operations, each a pass of its own. With ``centre``
    the direction of each point from it is taken inside the kernel (no [N, 3] temporary)."""
    degree = sh_degree_from_bases(sh.shape[1])
    sh = np.ascontiguousarray(sh.detach().cpu().numpy(), np.float32)
    centre = np.zeros(3, np.float32) if centre is None else centre
    if out is None:
        out = np.empty((sh.shape[0], 3), np.float32)
    elif out.shape != (sh.shape[0], 3) or out.dtype != np.float32:
        raise ValueError(f"out: expected [{sh.shape[0]}, 3] float32, got {out.dtype} {list(out.shape)}")
    if degree == 1:
        points = np.ascontiguousarray(dirs.detach().cpu().numpy(), np.float32)
        _sh1_colour_kernel(points, tuple(np.float32(c) for c in centre), sh, np.float32(SH_C0), np.float32(SH_C1), out)
    else:
        _sh_contract_kernel(sh_basis_at_points(dirs.detach().cpu().numpy(), centre, degree), sh, out)
    return torch.from_numpy(out)
