"""Eigen-decomposition of many symmetric 3x3 matrices (the decoder's per-voxel covariances).

``symmetric_eigh3_reference`` is ``torch.linalg.eigh`` in float64. ``symmetric_eigh3`` is the fast
path: cyclic Jacobi rotations in a numba kernel, one matrix per thread step, since a batched
LAPACK call over every decoded voxel would dominate a decode (`bench/decode.py` times both).
Both return eigenvalues in ascending order with
orthonormal eigenvectors as columns; eigenvectors are defined up to sign (and, for repeated
eigenvalues, up to a rotation within their eigenspace), so the two paths agree on eigenvalues and
on V diag(w) V^T, which is all a Gaussian's covariance depends on (held together by the tests).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

# Stop when the off-diagonal energy is below this share of the diagonal's (float64 round-off);
# cyclic Jacobi converges quadratically, so a 3x3 takes 4-6 sweeps, and the cap is never reached.
_RELATIVE_TOLERANCE = 1e-30
_MAX_SWEEPS = 50


def _check(cov: Tensor) -> None:
    if not isinstance(cov, Tensor) or cov.ndim != 3 or tuple(cov.shape[1:]) != (3, 3):
        shape = list(cov.shape) if isinstance(cov, Tensor) else type(cov).__name__
        raise ValueError(f"cov: expected a [N, 3, 3] tensor, got {shape}")


def symmetric_eigh3_reference(
    cov: Tensor,  # [N, 3, 3] symmetric
) -> tuple[Tensor, Tensor]:  # eigenvalues [N, 3] ascending, eigenvectors [N, 3, 3] as columns, float64
    """``torch.linalg.eigh`` in float64 (differentiable).

    Example:
        >>> w, v = symmetric_eigh3_reference(torch.diag(torch.tensor([3.0, 1.0, 2.0]))[None])
        >>> w.tolist()
        [[1.0, 2.0, 3.0]]
    """
    _check(cov)
    return torch.linalg.eigh(cov.double())


@numba.njit(cache=True, parallel=True)
def _jacobi_kernel(
    a: np.ndarray,  # [N, 3, 3] float64 symmetric, diagonalised in place (its diagonal: the eigenvalues)
    v: np.ndarray,  # [N, 3, 3] float64, out: the rotations' product, eigenvectors as columns
) -> None:
    for n in numba.prange(a.shape[0]):
        jacobi3(a, v, n)


@numba.njit(inline="always")
def _rotate(app, aqq, apq, arp, arq, v0p, v0q, v1p, v1q, v2p, v2q):
    """One Jacobi rotation (p, q) of the symmetric entries (r: the third index) and of V's columns
    p and q: the rotation's t = tan, c = cos, s = sin zero a_pq."""
    # t is the smaller root of t^2 + 2 theta t - 1 = 0 (the smaller angle: stable convergence)
    theta = (aqq - app) / (2.0 * apq)
    t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    c = 1.0 / np.sqrt(t * t + 1.0)
    s = t * c
    return (app - t * apq, aqq + t * apq, 0.0, c * arp - s * arq, s * arp + c * arq,
            c * v0p - s * v0q, s * v0p + c * v0q, c * v1p - s * v1q, s * v1p + c * v1q, c * v2p - s * v2q, s * v2p + c * v2q)


@numba.njit(inline="always")
def jacobi3(a, v, n):
    """Diagonalise a[n] in place by cyclic Jacobi rotations, their product into v[n] (eigenvectors
    as columns); inlined into the kernels that decompose one matrix per voxel. The six distinct
    entries and the nine of V stay in registers; each rotation J (J_pp = J_qq = c, J_pq = s,
    J_qp = -s) updates A <- J^T A J by the symmetric formulas (a_pq becomes exactly 0)."""
    a00, a01, a02, a11, a12, a22 = a[n, 0, 0], a[n, 0, 1], a[n, 0, 2], a[n, 1, 1], a[n, 1, 2], a[n, 2, 2]
    v00, v01, v02, v10, v11, v12, v20, v21, v22 = 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    for _ in range(_MAX_SWEEPS):
        off = a01 * a01 + a02 * a02 + a12 * a12
        diag = a00 * a00 + a11 * a11 + a22 * a22
        if off <= _RELATIVE_TOLERANCE * diag or off == 0.0:
            break
        # each rotation (p, q), with r the third index and V's columns p and q
        if a01 != 0.0:  # (p, q) = (0, 1), r = 2
            a00, a11, a01, a02, a12, v00, v01, v10, v11, v20, v21 = _rotate(a00, a11, a01, a02, a12, v00, v01, v10, v11, v20, v21)
        if a02 != 0.0:  # (p, q) = (0, 2), r = 1
            a00, a22, a02, a01, a12, v00, v02, v10, v12, v20, v22 = _rotate(a00, a22, a02, a01, a12, v00, v02, v10, v12, v20, v22)
        if a12 != 0.0:  # (p, q) = (1, 2), r = 0
            a11, a22, a12, a01, a02, v01, v02, v11, v12, v21, v22 = _rotate(a11, a22, a12, a01, a02, v01, v02, v11, v12, v21, v22)
    a[n, 0, 0], a[n, 1, 1], a[n, 2, 2] = a00, a11, a22
    a[n, 0, 1] = a[n, 1, 0] = a01
    a[n, 0, 2] = a[n, 2, 0] = a02
    a[n, 1, 2] = a[n, 2, 1] = a12
    v[n, 0, 0], v[n, 0, 1], v[n, 0, 2] = v00, v01, v02
    v[n, 1, 0], v[n, 1, 1], v[n, 1, 2] = v10, v11, v12
    v[n, 2, 0], v[n, 2, 1], v[n, 2, 2] = v20, v21, v22


def symmetric_eigh3(
    cov: Tensor,  # [N, 3, 3] symmetric (the symmetric part is used)
) -> tuple[Tensor, Tensor]:  # eigenvalues [N, 3] ascending, eigenvectors [N, 3, 3] as columns, float64
    """Eigenvalues and eigenvectors of symmetric 3x3 matrices by cyclic Jacobi rotations (numba);
    the same decomposition as `symmetric_eigh3_reference`, not differentiable. Matrices on an
    accelerator go to its batched library solver instead, where they are (numba reads host memory).

    Example:
        >>> cov = torch.tensor([[[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 5.0]]])
        >>> w, v = symmetric_eigh3(cov)
        >>> [round(x, 6) for x in w[0].tolist()]
        [1.0, 3.0, 5.0]
        >>> bool(torch.allclose(v[0] @ torch.diag(w[0]) @ v[0].T, cov[0].double()))
        True
    """
    _check(cov)
    a = cov.detach().to(torch.float64)
    a = (0.5 * (a + a.transpose(1, 2))).contiguous()
    if a.device.type != "cpu":
        return torch.linalg.eigh(a)
    vectors = torch.empty_like(a)
    if a.shape[0]:
        _jacobi_kernel(a.numpy(), vectors.numpy())
    values, order = torch.sort(torch.diagonal(a, dim1=1, dim2=2), dim=1, stable=True)  # ascending
    return values, torch.gather(vectors, 2, order[:, None, :].expand(-1, 3, -1))
