"""Eigen-decomposition of many symmetric 3x3 matrices (the decoder's per-voxel covariances).

``symmetric_eigh3_reference`` is ``torch.linalg.eigh`` in float64. ``symmetric_eigh3`` is the fast
path: cyclic Jacobi rotations in a numba kernel, 16 matrices at a time in vector lanes, since a batched
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
# cyclic Jacobi converges quadratically, so a 3x3 takes a few sweeps, and the cap is never reached.
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


# Matrices diagonalised side by side, one per vector lane: a Jacobi rotation is a chain of dependent
# square roots and divisions, so one matrix at a time waits on their latency, while the same rotation
# of 16 matrices at once is vector arithmetic (the loops over lanes vectorise).
LANES = 16
_CHUNK = 16 * LANES  # matrices a parallel task diagonalises


@numba.njit(inline="always")
def lane_scratch():
    """The working arrays of `jacobi3`, which a kernel makes once for many calls (a block or chunk
    of matrices), not once a matrix."""
    return np.empty((6, LANES)), np.empty((9, LANES)), np.empty(LANES, np.bool_)


@numba.njit(cache=True, parallel=True)
def _jacobi_kernel(
    a: np.ndarray,  # [N, 3, 3] float64 symmetric, diagonalised in place (its diagonal: the eigenvalues)
    v: np.ndarray,  # [N, 3, 3] float64, out: the rotations' product, eigenvectors as columns
) -> None:
    n = a.shape[0]
    for chunk in numba.prange(-(-n // _CHUNK)):  # a chunk's groups of LANES matrices share one scratch
        first = chunk * _CHUNK
        jacobi3(a, v, first, min(_CHUNK, n - first), lane_scratch())


@numba.njit(inline="always")
def _rotate(active, app, aqq, apq, arp, arq, vp0, vq0, vp1, vq1, vp2, vq2):
    """One Jacobi rotation (p, q) of each active lane (`LANES` of them): of the symmetric entries
    (r: the third index) and of V's columns p and q (rows 0-2). The rotation's t = tan, c = cos,
    s = sin zero a_pq; a lane that is not active, or whose a_pq is already 0, keeps every bit (its
    entries are selected, not multiplied by a rotation of angle 0, which could turn a -0.0 into 0.0)."""
    for lane in range(LANES):
        x = apq[lane]
        live = active[lane] & (x != 0.0)
        # t is the smaller root of t^2 + 2 theta t - 1 = 0 (the smaller angle: stable convergence)
        theta = (aqq[lane] - app[lane]) / (2.0 * (x if live else 1.0))
        t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0))
        t = -t if theta < 0.0 else t
        c = 1.0 / np.sqrt(t * t + 1.0)
        s = t * c
        app[lane] = app[lane] - t * x if live else app[lane]
        aqq[lane] = aqq[lane] + t * x if live else aqq[lane]
        apq[lane] = 0.0 if live else x
        rp, rq = arp[lane], arq[lane]
        arp[lane] = c * rp - s * rq if live else rp
        arq[lane] = s * rp + c * rq if live else rq
        p0, q0, p1, q1, p2, q2 = vp0[lane], vq0[lane], vp1[lane], vq1[lane], vp2[lane], vq2[lane]
        vp0[lane] = c * p0 - s * q0 if live else p0
        vq0[lane] = s * p0 + c * q0 if live else q0
        vp1[lane] = c * p1 - s * q1 if live else p1
        vq1[lane] = s * p1 + c * q1 if live else q1
        vp2[lane] = c * p2 - s * q2 if live else p2
        vq2[lane] = s * p2 + c * q2 if live else q2


@numba.njit(inline="always")
def jacobi3(a, v, first, count, scratch):
    """Diagonalise a[first:first + count] in place by cyclic Jacobi rotations, their products into
    v[first:first + count] (eigenvectors as columns); inlined into the kernels that decompose one
    matrix per voxel (inlined, the loops over lanes vectorise). `LANES` matrices go side by side,
    their sweeps in step until each has converged; one that has stops turning, so that each gets the
    rotations it would get alone, whatever matrices share its lanes: a voxel decodes to the same bits
    in any decode. Each rotation J (J_pp = J_qq = c, J_pq = s, J_qp = -s) updates A <- J^T A J by the
    symmetric formulas (a_pq becomes exactly 0). ``scratch``: `lane_scratch()`."""
    # a00 a01 a02 a11 a12 a22 of each lane; V, row-major; the lanes not yet converged
    m, r, active = scratch
    for start in range(first, first + count, LANES):
        n = min(LANES, first + count - start)
        m[:] = 0.0  # spare lanes: the zero matrix, converged from the start
        r[:] = 0.0
        r[0], r[4], r[8] = 1.0, 1.0, 1.0
        for lane in range(n):
            i = start + lane
            m[0, lane], m[1, lane], m[2, lane] = a[i, 0, 0], a[i, 0, 1], a[i, 0, 2]
            m[3, lane], m[4, lane], m[5, lane] = a[i, 1, 1], a[i, 1, 2], a[i, 2, 2]
        for _ in range(_MAX_SWEEPS):
            converged = True
            for lane in range(LANES):
                off = m[1, lane] * m[1, lane] + m[2, lane] * m[2, lane] + m[4, lane] * m[4, lane]
                diag = m[0, lane] * m[0, lane] + m[3, lane] * m[3, lane] + m[5, lane] * m[5, lane]
                active[lane] = not (off <= _RELATIVE_TOLERANCE * diag or off == 0.0)
                converged &= not active[lane]
            if converged:
                break
            _rotate(active, m[0], m[3], m[1], m[2], m[4], r[0], r[1], r[3], r[4], r[6], r[7])  # (p, q) = (0, 1), r = 2
            _rotate(active, m[0], m[5], m[2], m[1], m[4], r[0], r[2], r[3], r[5], r[6], r[8])  # (0, 2), r = 1
            _rotate(active, m[3], m[5], m[4], m[1], m[2], r[1], r[2], r[4], r[5], r[7], r[8])  # (1, 2), r = 0
        for lane in range(n):
            i = start + lane
            a[i, 0, 0], a[i, 1, 1], a[i, 2, 2] = m[0, lane], m[3, lane], m[5, lane]
            a[i, 0, 1] = a[i, 1, 0] = m[1, lane]
            a[i, 0, 2] = a[i, 2, 0] = m[2, lane]
            a[i, 1, 2] = a[i, 2, 1] = m[4, lane]
            for j in range(3):
                for k in range(3):
                    v[i, j, k] = r[3 * j + k, lane]


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
