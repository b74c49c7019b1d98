"""Splat shapes straight from a voxel's stored position moments: the fast path of the decoder's geometry.

The reference takes three steps over whole columns: `fields.fields_from_sums` turns the gathered
sums into the centroid and covariance (float64, then float32), `GaussianDecoder.base_shapes`
decomposes the covariance (`decode.symmetric_eigh3`), sorts the axes, scales and clamps the stds
and turns the axes into a quaternion. Each step reads and writes every row, and the gathers and
temporaries cost more than the arithmetic. `voxel_shapes` does the same per voxel in one numba
pass, reading the scene's stored moments in place at the decoded rows (made sums as `stored.raw_sums`
makes them), in the same order of operations and
the same precisions (float32 where the reference rounds to float32), so that the two agree to the
last bit or so; `tests/scene/test_shapes.py` holds it to the reference.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ..decode.decoder import FOOTPRINT_GAIN, GaussianDecoder
from ..decode.eigen import jacobi3, lane_scratch
from ..config import KEY_BITS, KEY_OFFSET
from .half import from_half
from .stored import CENTRAL, MEAN, factor, sum_of

_CHUNK = 256  # voxels per parallel task, each with its own small scratch (cache-resident)
# pos_cov's columns (xx xy xz yy yz zz) at (row, column) of the symmetric 3x3 (as fields._SQ_INDEX)
_SQ = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], np.int64)


@numba.njit(parallel=True, cache=True)
def _voxel_shapes_kernel(
    rows,  # [N] int64 scene rows to decode
    keys,  # [V] int64 packed lattice keys
    rep_local,  # [V, 3] float16 bits: representative positions (local voxel units)
    pos_mean,  # [V, 3] float16 bits (uint16): sum W x / R_scene (local voxel units)
    pos_cov,  # [V, 6] float16 bits: the central second moment over R_scene, upper triangle (`stored`)
    r_sum,  # [V] float32 R_scene
    voxel_size, eps, gain, lo_normal, lo_plane, hi,  # float64 | float32 gain and clamps
    centroid,  # [N, 3] float32 out
    std,  # [N, 3] float32 out, voxel units
    quats,  # [N, 4] float32 out, wxyz
):
    mask = (1 << KEY_BITS) - 1
    vv = np.float32(voxel_size * voxel_size)
    one, zero = np.float32(1.0), np.float32(0.0)  # a position moment's means: scale 1, offset 0 (`stored.column_rules`)
    for chunk in numba.prange(-(-rows.shape[0] // _CHUNK)):  # scratch per chunk: small, cache-resident
        first = chunk * _CHUNK
        a = np.empty((_CHUNK, 3, 3))  # the covariance, diagonalised in place
        vec = np.empty((_CHUNK, 3, 3))  # its eigenvectors
        work = np.empty((_CHUNK, 3, 3))  # voxel centre, representative, centroid (local units)
        rotations = np.empty((_CHUNK, 3, 3), np.float32)
        lanes = lane_scratch()
        last = min(rows.shape[0], first + _CHUNK)
        for i in range(first, last):  # the chunk's covariances
            li = i - first
            row = rows[i]
            key = keys[row]
            c, rep, m = work[li, 0], work[li, 1], work[li, 2]
            c[0] = float(((key >> (2 * KEY_BITS)) & mask) - KEY_OFFSET) + 0.5
            c[1] = float(((key >> KEY_BITS) & mask) - KEY_OFFSET) + 0.5
            c[2] = float((key & mask) - KEY_OFFSET) + 0.5
            r = r_sum[row]
            den = float(np.float32(r + np.float32(eps)))
            for j in range(3):
                rep[j] = float(from_half(rep_local[row, j]))
                m[j] = (float(sum_of(from_half(pos_mean[row, j]), MEAN, one, one, r)) + eps * rep[j]) / den
                centroid[i, j] = np.float32((c[j] + m[j]) * voxel_size)
            for j in range(3):  # covariance: float64, stored as float32, back to voxel units in float32
                for k in range(3):
                    raw = sum_of(from_half(pos_cov[row, _SQ[j, k]]), CENTRAL, factor(pos_mean, row, j, one, zero),
                                 factor(pos_mean, row, k, one, zero), r)  # the sums as `stored.raw_sums` has them
                    second = (float(raw) + eps * rep[j] * rep[k]) / den
                    a[li, j, k] = float(np.float32((second - m[j] * m[k]) * voxel_size * voxel_size) / vv)
            for j in range(3):
                for k in range(j + 1, 3):
                    sym = float(np.float32(0.5) * (np.float32(a[li, j, k]) + np.float32(a[li, k, j])))
                    a[li, j, k] = sym
                    a[li, k, j] = sym
        jacobi3(a, vec, 0, last - first, lanes)  # diagonalised together (in vector lanes)
        for i in range(first, last):  # their axes, stds and quaternions
            li = i - first
            # ascending eigenvalues, stable (as torch.sort(stable=True))
            d0, d1, d2 = a[li, 0, 0], a[li, 1, 1], a[li, 2, 2]
            o0, o1, o2 = 0, 1, 2
            if d1 < d0:
                o0, o1 = 1, 0
            if d2 < a[li, o1, o1]:
                o1, o2 = 2, o1
                if d2 < a[li, o0, o0]:
                    o0, o1 = 2, o0
            order = (o0, o1, o2)
            r = rotations[li]
            for k in range(3):
                d = a[li, order[k], order[k]]
                s = np.float32(np.sqrt(d if d > 0.0 else 0.0)) * gain
                lo = lo_normal if k == 0 else lo_plane
                s = s if s > lo else lo
                std[i, k] = s if s < hi else hi
                for j in range(3):
                    r[j, k] = np.float32(vec[li, j, order[k]])
            det = (float(r[0, 0]) * (float(r[1, 1]) * r[2, 2] - float(r[1, 2]) * r[2, 1])
                   - float(r[0, 1]) * (float(r[1, 0]) * r[2, 2] - float(r[1, 2]) * r[2, 0])
                   + float(r[0, 2]) * (float(r[1, 0]) * r[2, 1] - float(r[1, 1]) * r[2, 0]))
            if det < 0.0:
                for j in range(3):
                    r[j, 2] = -r[j, 2]
            # rotation -> quaternion: the candidate whose squared component is largest (matrix_to_quaternion)
            one = np.float32(1.0)
            trace = r[0, 0] + r[1, 1] + r[2, 2]
            pick, best = 0, trace
            for k in range(3):
                if r[k, k] > best:
                    pick, best = k + 1, r[k, k]
            q = quats[i]
            if pick == 0:
                q[0], q[1], q[2], q[3] = one + trace, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
            elif pick == 1:
                q[0], q[1], q[2], q[3] = r[2, 1] - r[1, 2], one + r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]
            elif pick == 2:
                q[0], q[1], q[2], q[3] = r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], one - r[0, 0] + r[1, 1] - r[2, 2], r[1, 2] + r[2, 1]
            else:
                q[0], q[1], q[2], q[3] = r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], one - r[0, 0] - r[1, 1] + r[2, 2]
            norm = np.float32(np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]))
            norm = norm if norm > np.float32(1e-12) else np.float32(1e-12)
            sign = np.float32(-1.0) if q[0] / norm < 0 else one
            for k in range(4):
                q[k] = sign * (q[k] / norm)


def voxel_shapes(
    sums: dict[str, np.ndarray],  # the scene's sums (`Scene.sums` or `decode_inputs().sums`), every row
    rows: np.ndarray,  # [N] int64 rows to decode
    voxel_size: float,
    eps: float,  # `SceneConfig.research.eps`
    decoder: GaussianDecoder,  # its clamps
) -> tuple[Tensor, Tensor, Tensor]:  # centroid [N, 3], std [N, 3] (voxel units), quats [N, 4]: float32
    """`GaussianDecoder.base_shapes` of `fields_from_sums` of ``rows``, from the sums in place."""
    rows = np.ascontiguousarray(rows, np.int64)
    n = rows.shape[0]
    centroid, std, quats = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty((n, 4), np.float32)
    if n:
        f32 = np.float32
        _voxel_shapes_kernel(
            rows, sums["keys"], sums["rep_local"].view(np.uint16), sums["pos_mean"].view(np.uint16),
            sums["pos_cov"].view(np.uint16), sums["r_sum"],
            float(voxel_size), float(eps), f32(FOOTPRINT_GAIN), f32(decoder.min_thickness), f32(decoder.min_extent),
            f32(decoder.max_extent), centroid, std, quats,
        )  # fmt: skip
    return torch.from_numpy(centroid), torch.from_numpy(std), torch.from_numpy(quats)
