"""Numba kernels of the streaming fold: an open-addressing int64 -> voxel-index hash and one pass
that decides representatives, rescales on replacement and accumulates the weighted sums.

Layout: voxel keys pack (i, j, k) + KEY_OFFSET into 21 bits each; ``table`` holds voxel indices
(-1 = empty) and the key is read back from ``keys[index]``, so the table costs 4 bytes a slot.
Positions are accumulated in *local voxel units* (offset from the voxel centre, in [-0.5, 0.5]),
which keeps second moments well conditioned in float32 wherever the voxel sits in the world.

Weighting modes (the ablations): 0 full, 1 no_reliability, 2 no_similarity, 3 average. Modes 1 and 3
treat every reliability as 1, so the representative is the voxel's first observation.
"""

from __future__ import annotations

import numba
import numpy as np

from .config import KEY_BITS, KEY_OFFSET

MODE_CODES = {"full": 0, "no_reliability": 1, "no_similarity": 2, "average": 3}
_KEY_LIMIT = 1 << KEY_BITS
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(inline="always")
def _slot(key, mask):
    h = np.uint64(key) * _HASH_MULT
    return np.int64((h >> np.uint64(29)) & np.uint64(mask))


@numba.njit(inline="always")
def _find(table, keys, key, mask):
    """Index of ``key`` (>= 0), or -1 - slot of the empty slot where it would go."""
    s = _slot(key, mask)
    while True:
        idx = table[s]
        if idx < 0:
            return -1 - s
        if keys[idx] == key:
            return idx
        s = (s + 1) & mask


@numba.njit(inline="always")
def _voxel_coord(x, inv_voxel):
    return np.int64(np.floor(x * inv_voxel))


@numba.njit(inline="always")
def _pack(i, j, k):
    a, b, c = i + KEY_OFFSET, j + KEY_OFFSET, k + KEY_OFFSET
    if a < 0 or b < 0 or c < 0 or a >= _KEY_LIMIT or b >= _KEY_LIMIT or c >= _KEY_LIMIT:
        return np.int64(-1)
    return (a << (2 * KEY_BITS)) | (b << KEY_BITS) | c


@numba.njit(cache=True)
def voxel_keys_kernel(points, inv_voxel, out):
    """Keys of the voxels holding ``points`` ([M, 3] float32); -1 outside the lattice."""
    for i in range(points.shape[0]):
        out[i] = _pack(_voxel_coord(points[i, 0], inv_voxel), _voxel_coord(points[i, 1], inv_voxel),
                       _voxel_coord(points[i, 2], inv_voxel))


@numba.njit(cache=True)
def rebuild_table_kernel(table, keys, n_voxels):
    table[:] = -1
    mask = table.shape[0] - 1
    for idx in range(n_voxels):
        table[-1 - _find(table, keys, keys[idx], mask)] = idx


@numba.njit(cache=True)
def resolve_kernel(obs_keys, table, keys, local_table, new_keys, obs_voxel):
    """Phase A (reads the scene, writes only scratch): map observations to existing voxels, and
    number the keys not yet in the scene in first-occurrence order. Returns the count of new keys.

    obs_voxel[i] = voxel index (>= 0), -2 - j for the j-th new key, or -1 outside the lattice.
    """
    mask = table.shape[0] - 1
    local_mask = local_table.shape[0] - 1
    local_table[:] = -1
    n_new = 0
    for i in range(obs_keys.shape[0]):
        key = obs_keys[i]
        if key < 0:
            obs_voxel[i] = -1
            continue
        r = _find(table, keys, key, mask)
        if r >= 0:
            obs_voxel[i] = r
            continue
        r = _find(local_table, new_keys, key, local_mask)
        if r >= 0:
            obs_voxel[i] = -2 - r
        else:
            local_table[-1 - r] = n_new
            new_keys[n_new] = key
            obs_voxel[i] = -2 - n_new
            n_new += 1
    return n_new


@numba.njit(inline="always")
def _inv_norm(a):
    n2 = np.float32(0.0)
    for c in range(a.shape[0]):
        n2 += a[c] * a[c]
    return np.float32(1.0) / np.sqrt(n2) if n2 > np.float32(1e-20) else np.float32(0.0)


@numba.njit(inline="always")
def _dot(a, b):
    d = np.float32(0.0)
    for c in range(a.shape[0]):
        d += a[c] * b[c]
    return d


@numba.njit(inline="always")
def _scale_row(row, s):
    for c in range(row.shape[0]):
        row[c] *= s


@numba.njit(cache=True, parallel=True)
def fold_kernel(
    # scene state (rows >= n_voxels are zero; local is -1 outside a fold)
    table, keys, rep_r, rep_f, rep_pos, rep_rgb, r_sum, f_sum, rgb_sum, pos_sum, pos_sq,
    sh_a, sh_b, label_sum, label_w, n_obs, local,
    n_voxels, mode, inv_voxel,
    # the frame's evidence and phase A's result
    new_keys, n_new, obs_voxel, rel, feat, rgb, points, sh_basis, labels, has_labels,
    # scratch [M] ([M + 1] for start)
    touched, best, feat_inv_norm, rep_inv_norm, obs_slot, start, order,
):
    """Phase B: insert the new voxels, pick each touched voxel's frame-best observation, replace
    representatives that it beats (rescaling the old sums by max(0, cos(old rep, new rep))), then
    accumulate W = R * max(0, cos(F, F_rep)) weighted sums. Returns (touched, switches).

    Besides F, colour and position moments, W accumulates the normal equations of the per-voxel
    SH colour fit: sh_a = upper triangle of sum W b b^T without its (0, 0) entry (= C0^2 R_scene),
    sh_b = sum W b_k (c - 1/2) for k >= 1 (the DC row is C0 (sum W c - R_scene / 2)); b is the
    observation's SH basis of its view direction.

    The frame's observations are grouped by voxel (a stable counting sort), then voxels are summed
    in parallel, each over its own observations in frame order: a voxel's rows stay in cache while
    it is summed, and the result is bit-identical for any thread count."""
    mask = table.shape[0] - 1
    for j in range(n_new):
        vi = n_voxels + j
        keys[vi] = new_keys[j]
        table[-1 - _find(table, keys, new_keys[j], mask)] = vi
        rep_r[vi] = np.float32(-1.0)  # below any reliability: the first observation takes it
    uses_rel = mode == 0 or mode == 2
    uses_sim = mode == 0 or mode == 1
    has_label_arrays = label_sum.shape[1] > 0
    K = sh_basis.shape[1]
    M = obs_voxel.shape[0]
    for i in numba.prange(M):
        feat_inv_norm[i] = _inv_norm(feat[i])
    # 1) frame-local best observation per voxel (first maximum wins, as in the batch rule)
    n_touched = 0
    for i in range(M):
        vi = obs_voxel[i]
        if vi == -1:
            continue
        if vi < -1:
            vi = n_voxels + (-2 - vi)
            obs_voxel[i] = vi
        r = rel[i] if uses_rel else np.float32(1.0)
        if local[vi] < 0:
            local[vi] = n_touched
            touched[n_touched] = vi
            best[n_touched] = i
            n_touched += 1
            obs_slot[i] = n_touched - 1
        else:
            obs_slot[i] = local[vi]
            b = best[local[vi]]
            rb = rel[b] if uses_rel else np.float32(1.0)
            if r > rb:
                best[local[vi]] = i
    # 2) representatives: a strictly more reliable observation replaces the running one
    switches = 0
    for t in numba.prange(n_touched):
        vi = touched[t]
        b = best[t]
        rb = rel[b] if uses_rel else np.float32(1.0)
        if rb > rep_r[vi]:
            if n_obs[vi] > 0:
                switches += 1
                s = np.float32(1.0)
                if uses_sim:
                    s = max(np.float32(0.0), _dot(rep_f[vi], feat[b]) * _inv_norm(rep_f[vi]) * feat_inv_norm[b])
                if s != np.float32(1.0):
                    r_sum[vi] *= s
                    _scale_row(f_sum[vi], s)
                    _scale_row(rgb_sum[vi], s)
                    _scale_row(pos_sum[vi], s)
                    _scale_row(pos_sq[vi], s)
                    _scale_row(sh_a[vi], s)
                    _scale_row(sh_b[vi], s)
                    if has_label_arrays:
                        label_w[vi] *= s
                        _scale_row(label_sum[vi], s)
            rep_r[vi] = rb
            rep_f[vi, :] = feat[b]
            rep_pos[vi, :] = points[b]
            for c in range(3):  # colours are u8 / 255, so this round trip is exact
                rep_rgb[vi, c] = np.uint8(rgb[b, c] * np.float32(255.0) + np.float32(0.5))
        rep_inv_norm[t] = _inv_norm(rep_f[vi])
    # 3) group observations by voxel, keeping frame order within each voxel (counting sort)
    start[: n_touched + 1] = 0
    for i in range(M):
        if obs_voxel[i] >= 0:
            start[obs_slot[i] + 1] += 1
    for t in range(n_touched):
        start[t + 1] += start[t]
    for i in range(M):
        if obs_voxel[i] >= 0:
            t = obs_slot[i]
            order[start[t]] = i
            start[t] += 1
    for t in range(n_touched, 0, -1):  # the fill advanced each start to the next one's: shift back
        start[t] = start[t - 1]
    start[0] = 0
    # 4) weighted sums, voxels in parallel, each voxel's observations in frame order
    for t in numba.prange(n_touched):
        vi = touched[t]
        for j in range(start[t], start[t + 1]):
            i = order[j]
            w = rel[i] if uses_rel else np.float32(1.0)
            if uses_sim:
                cos = _dot(feat[i], rep_f[vi]) * feat_inv_norm[i] * rep_inv_norm[t]
                w = w * max(np.float32(0.0), cos)
            n_obs[vi] += 1
            r_sum[vi] += w
            for c in range(f_sum.shape[1]):
                f_sum[vi, c] += w * feat[i, c]
            lx = points[i, 0] * inv_voxel - (np.floor(points[i, 0] * inv_voxel) + np.float32(0.5))
            ly = points[i, 1] * inv_voxel - (np.floor(points[i, 1] * inv_voxel) + np.float32(0.5))
            lz = points[i, 2] * inv_voxel - (np.floor(points[i, 2] * inv_voxel) + np.float32(0.5))
            for c in range(3):
                rgb_sum[vi, c] += w * rgb[i, c]
            pos_sum[vi, 0] += w * lx
            pos_sum[vi, 1] += w * ly
            pos_sum[vi, 2] += w * lz
            pos_sq[vi, 0] += w * lx * lx
            pos_sq[vi, 1] += w * lx * ly
            pos_sq[vi, 2] += w * lx * lz
            pos_sq[vi, 3] += w * ly * ly
            pos_sq[vi, 4] += w * ly * lz
            pos_sq[vi, 5] += w * lz * lz
            if K > 1:
                idx = 0
                for p in range(K):
                    wb = w * sh_basis[i, p]
                    for q in range(p, K):
                        if p > 0 or q > 0:
                            sh_a[vi, idx] += wb * sh_basis[i, q]
                            idx += 1
                    if p > 0:
                        for c in range(3):
                            sh_b[vi, 3 * (p - 1) + c] += wb * (rgb[i, c] - np.float32(0.5))
            if has_labels:
                label_w[vi] += w
                for c in range(label_sum.shape[1]):
                    label_sum[vi, c] += w * labels[i, c]
    for t in range(n_touched):
        local[touched[t]] = -1
    return n_touched, switches
