"""The streaming fold's numba kernel: one pass that decides representatives, rescales on replacement
and accumulates the weighted sums into each voxel's row (`VoxelRows`), the voxels found through the
lattice's hash table (`hashing`).

Positions are accumulated in *local voxel units* (offset from the voxel centre, in [-0.5, 0.5]),
which keeps second moments well conditioned in float32 wherever the voxel sits in the world.

The weighting (the ablations) reaches the kernels as two flags, `SceneConfig.uses_reliability` and
`SceneConfig.uses_similarity`; without reliability every R is 1, so the representative is the
voxel's first observation.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import binding as llvm_binding
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from .hashing import find_voxel, home_slot
from .stored import load_row, quantize_direction, store_row

# LLVM's prefetch intrinsic takes an opaque pointer from LLVM 15 on, an i8* before
_PREFETCH = "llvm.prefetch.p0" if llvm_binding.llvm_version_info[0] >= 15 else "llvm.prefetch.p0i8"


@intrinsic
def _prefetch(typingctx, array, row, column):
    """Ask for the cache line holding ``array[row, column]`` (a 2-D array) ahead of its use; a hint
    with no effect on any result. numba has no prefetch of its own."""

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        at = [context.cast(builder, v, t, types.intp) for v, t in zip(args[1:], signature.args[1:])]
        pointer = builder.bitcast(cgutils.get_item_pointer(context, builder, array_type, view, at), ir.IntType(8).as_pointer())
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [pointer.type, ir.IntType(32), ir.IntType(32), ir.IntType(32)]), _PREFETCH)
        # read, keep in all cache levels, data cache
        builder.call(fn, [pointer, ir.Constant(ir.IntType(32), 0), ir.Constant(ir.IntType(32), 3), ir.Constant(ir.IntType(32), 1)])
        return context.get_dummy_value()

    return types.void(array, row, column), codegen




class VoxelRows:
    """Column layout of the per-voxel float32 record the fold works on: the representative, then every
    weighted sum (the map stores it narrower: `stored.StoredRows`).

    One contiguous row per voxel (instead of one array per field) keeps a touched voxel's whole
    state in a few adjacent cache lines, where one array per field costs a cache miss per field.

    Columns, in order: rep_r, rep_f [L], rep_pos [3] (local voxel units) | r_sum, f_sum [L], rgb_sum [3],
    pos_sum [3], pos_sq [6], sh_a [Wa], sh_b [Wb], and with S label channels label_w, label_sum [S]. Everything
    from r_sum on is a weighted sum (rescaled together when a representative is replaced).
    """

    def __init__(self, feature_dim: int, sh_widths: tuple[int, int], label_dim: int = 0):
        shapes = {"rep_r": (), "rep_f": (feature_dim,), "rep_pos": (3,), "r_sum": (), "f_sum": (feature_dim,),
                  "rgb_sum": (3,), "pos_sum": (3,), "pos_sq": (6,), "sh_a": (sh_widths[0],), "sh_b": (sh_widths[1],)}
        if label_dim:
            shapes |= {"label_w": (), "label_sum": (label_dim,)}
        self.columns: dict[str, tuple[int, tuple[int, ...]]] = {}  # name -> (first column, field shape per voxel)
        col = 0
        for name, shape in shapes.items():
            self.columns[name] = (col, shape)
            col += shape[0] if shape else 1
        self.width = col
        self.label_dim = label_dim

    def field(self, rows: np.ndarray, name: str) -> np.ndarray:
        """View of one field of ``rows`` ([V, width]): [V] for scalars, [V, n] for vectors (n may be 0)."""
        first, shape = self.columns[name]
        return rows[:, first] if not shape else rows[:, first: first + shape[0]]

    def offsets(self) -> tuple[int, ...]:
        """(rep_f, rep_pos, r_sum, f_sum, rgb_sum, pos_sum, pos_sq, sh_a, sh_b, label_w, label_sum) columns for the kernel
        (rep_r is column 0; label columns are -1 without labels)."""
        names = ("rep_f", "rep_pos", "r_sum", "f_sum", "rgb_sum", "pos_sum", "pos_sq", "sh_a", "sh_b", "label_w", "label_sum")
        return tuple(self.columns[n][0] if n in self.columns else -1 for n in names)



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


PREFETCH_AHEAD = 8  # voxels ahead whose rows `fold_kernel` asks for
OBS_PREFETCH_AHEAD = 2  # voxels ahead whose observations' evidence it asks for


@numba.njit(cache=True, parallel=True)
def fold_kernel(
    # scene state (rows >= n_voxels are zero): the stored records (`stored.StoredRows`) and, per
    # thread, a float32 working record [threads, width] that each voxel is folded in
    table, keys, rows, half, wide_cols, direction, half_cols, half_kind, factor_cols, factor_affine, work, rep_rgb,
    n_obs, n_voxels, offsets, uses_rel, uses_sim, weight_floor, inv_voxel,
    # phase A's result
    n_touched, touched, new_keys, n_new, best, head, next_obs,
    # the frame's evidence
    rel, feat, rgb, points, sh_basis, labels, has_labels,
    # with keep_before: the existing rows touched, copied before they change (slot: scratch [>= n_touched])
    keep_before, before_slot, before_index, before_rows, before_half, before_rgb, before_n_obs,
):
    """Phase B: insert the new voxels; then, per touched voxel, replace its representative if the
    frame-best observation beats it (rescaling the old sums by max(0, cos(old rep, new rep))) and
    accumulate W = max(R * max(0, cos(F, F_rep)), weight_floor * R_rep) weighted sums into its row
    (`VoxelRows`, loaded from the stored record and stored back: `stored`). Returns the
    representative switches. With ``keep_before`` it first copies each existing voxel's stored
    record, colour and count into the ``before_*`` arrays (one entry per existing touched voxel, in
    slot order), for an undo record: the copy reads the record the visit reads anyway.

    Besides F, colour and position moments, W accumulates the normal equations of the per-voxel
    SH colour fit: sh_a = upper triangle of sum W b b^T without its (0, 0) entry (= C0^2 R_scene),
    sh_b = sum W b_k (c - 1/2) for k >= 1 (the DC row is C0 (sum W c - R_scene / 2)); b is the
    observation's SH basis of its view direction.

    Voxels are summed in parallel, each over its own observations in frame order (phase A's
    chains): the result is bit-identical for any thread count. A voxel's representative and its
    sums are done in one visit, so that its row comes into the cache once (on a room-scale map most
    rows are far out of cache)."""
    REP_F, REP_POS, R_SUM, F_SUM, RGB_SUM, POS_SUM, POS_SQ, SH_A, SH_B, LABEL_W, LABEL_SUM = offsets
    L = feat.shape[1]
    S = labels.shape[1]
    D = work.shape[1]
    mask = table.shape[0] - 1
    for j in range(n_new):
        vi = n_voxels + j
        keys[vi] = new_keys[j]
        table[-1 - find_voxel(table, keys, new_keys[j], mask)] = vi
    K = sh_basis.shape[1]
    kept = 0
    for t in range(n_touched):
        if touched[t] < 0:
            touched[t] = n_voxels + (-2 - touched[t])
        elif keep_before:
            before_slot[t] = kept
            kept += 1
    switches = 0
    for t in numba.prange(n_touched):
        # the row of the voxel PREFETCH_AHEAD on, asked for now: on a room-scale map the rows a frame
        # touches lie scattered over far more memory than the caches hold
        if t + PREFETCH_AHEAD < n_touched:
            ahead = touched[t + PREFETCH_AHEAD]
            _prefetch(rows, ahead, 0)
            _prefetch(rows, ahead, rows.shape[1] - 1)
            for c in range(0, half.shape[1], 32):
                _prefetch(half, ahead, c)
            _prefetch(half, ahead, half.shape[1] - 1)
        # and the evidence of the voxel OBS_PREFETCH_AHEAD on: its observations' lines lie a few image
        # rows apart, and the sums below are too long a loop for the CPU to reach the next ones itself
        if t + OBS_PREFETCH_AHEAD < n_touched:
            j = head[t + OBS_PREFETCH_AHEAD]
            while j >= 0:
                _prefetch(feat, j, 0)
                _prefetch(sh_basis, j, 0)
                _prefetch(points, j, 0)
                _prefetch(rgb, j, 0)
                j = next_obs[j]
        vi = touched[t]
        thread = numba.get_thread_id()  # below NUMBA_NUM_THREADS (the rows of work) in every threading layer
        row = work[thread]
        if vi >= n_voxels:  # a new voxel (written first here, in parallel: fresh memory costs a page fault)
            for c in range(D):  # what loading its all-zero record gives, without converting it column by column
                row[c] = np.float32(0.0)
            row[0] = np.float32(-1.0)  # rep_r below any reliability: the first observation takes it
        else:
            load_row(rows, half, vi, wide_cols, direction, half_cols, half_kind, factor_cols, factor_affine, R_SUM, row)
            if keep_before:
                k = before_slot[t]
                before_index[k] = vi
                for c in range(rows.shape[1]):
                    before_rows[k, c] = rows[vi, c]
                for c in range(half.shape[1]):
                    before_half[k, c] = half[vi, c]
                for c in range(3):
                    before_rgb[k, c] = rep_rgb[vi, c]
                before_n_obs[k] = n_obs[vi]
        # 1) its representative: a strictly more reliable observation replaces the running one
        b = best[t]
        rb = rel[b] if uses_rel else np.float32(1.0)
        if rb > row[0]:
            if n_obs[vi] > 0:
                switches += 1
                if uses_sim:
                    s = max(np.float32(0.0), _dot(row[REP_F: REP_F + L], feat[b]) * _inv_norm(row[REP_F: REP_F + L]) * _inv_norm(feat[b]))
                    if s != np.float32(1.0):
                        for c in range(R_SUM, D):
                            row[c] *= s
            row[0] = rb
            for c in range(L):
                row[REP_F + c] = feat[b, c]
            quantize_direction(row, REP_F, L)  # what the map keeps of it (`stored`), from now on
            for c in range(3):  # in local voxel units, as the observations' moments (colours are u8 / 255: exact)
                row[REP_POS + c] = points[b, c] * inv_voxel - (np.floor(points[b, c] * inv_voxel) + np.float32(0.5))
                rep_rgb[vi, c] = np.uint8(rgb[b, c] * np.float32(255.0) + np.float32(0.5))
        rep_inv_norm = _inv_norm(row[REP_F: REP_F + L])
        floor_w = weight_floor * row[0]  # no observation weighs less than this share of the representative's
        # 2) its weighted sums over its observations in frame order (phase A's chain); the
        # fixed-size sums go through registers and are added to the row once
        rep_f, f_sum = row[REP_F: REP_F + L], row[F_SUM: F_SUM + L]
        r_acc = c0 = c1 = c2 = px = py = pz = qxx = qxy = qxz = qyy = qyz = qzz = np.float32(0.0)
        a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = np.float32(0.0)
        s1r = s1g = s1b = s2r = s2g = s2b = s3r = s3g = s3b = np.float32(0.0)
        count = 0
        i = head[t]
        while i >= 0:
            count += 1
            f = feat[i]
            w = rel[i] if uses_rel else np.float32(1.0)
            if uses_sim:
                w = w * max(np.float32(0.0), _dot(f, rep_f) * _inv_norm(f) * rep_inv_norm)
            w = max(w, floor_w)
            r_acc += w
            for c in range(L):
                f_sum[c] += w * f[c]
            c0 += w * rgb[i, 0]
            c1 += w * rgb[i, 1]
            c2 += w * rgb[i, 2]
            lx = points[i, 0] * inv_voxel - (np.floor(points[i, 0] * inv_voxel) + np.float32(0.5))
            ly = points[i, 1] * inv_voxel - (np.floor(points[i, 1] * inv_voxel) + np.float32(0.5))
            lz = points[i, 2] * inv_voxel - (np.floor(points[i, 2] * inv_voxel) + np.float32(0.5))
            wx, wy, wz = w * lx, w * ly, w * lz
            px += wx
            py += wy
            pz += wz
            qxx += wx * lx
            qxy += wx * ly
            qxz += wx * lz
            qyy += wy * ly
            qyz += wy * lz
            qzz += wz * lz
            if K == 4:  # degree 1 (the default): the 18 sums in registers, same order as below
                wb0, wb1, wb2, wb3 = w * sh_basis[i, 0], w * sh_basis[i, 1], w * sh_basis[i, 2], w * sh_basis[i, 3]
                b1, b2, b3 = sh_basis[i, 1], sh_basis[i, 2], sh_basis[i, 3]
                r0, g0, bl0 = rgb[i, 0] - np.float32(0.5), rgb[i, 1] - np.float32(0.5), rgb[i, 2] - np.float32(0.5)
                a01 += wb0 * b1
                a02 += wb0 * b2
                a03 += wb0 * b3
                a11 += wb1 * b1
                a12 += wb1 * b2
                a13 += wb1 * b3
                a22 += wb2 * b2
                a23 += wb2 * b3
                a33 += wb3 * b3
                s1r += wb1 * r0
                s1g += wb1 * g0
                s1b += wb1 * bl0
                s2r += wb2 * r0
                s2g += wb2 * g0
                s2b += wb2 * bl0
                s3r += wb3 * r0
                s3g += wb3 * g0
                s3b += wb3 * bl0
            elif K > 1:
                idx = SH_A
                for p in range(K):
                    wb = w * sh_basis[i, p]
                    for q in range(p, K):
                        if p > 0 or q > 0:
                            row[idx] += wb * sh_basis[i, q]
                            idx += 1
                    if p > 0:
                        for c in range(3):
                            row[SH_B + 3 * (p - 1) + c] += wb * (rgb[i, c] - np.float32(0.5))
            if has_labels:  # a row of zeros (a class map's pixel of no class) is no label evidence
                labelled = False
                for c in range(S):
                    labelled = labelled or labels[i, c] != 0
                if labelled:
                    row[LABEL_W] += w
                    for c in range(S):
                        row[LABEL_SUM + c] += w * labels[i, c]
            i = next_obs[i]
        n_obs[vi] += count
        row[R_SUM] += r_acc
        row[RGB_SUM] += c0
        row[RGB_SUM + 1] += c1
        row[RGB_SUM + 2] += c2
        row[POS_SUM] += px
        row[POS_SUM + 1] += py
        row[POS_SUM + 2] += pz
        row[POS_SQ] += qxx
        row[POS_SQ + 1] += qxy
        row[POS_SQ + 2] += qxz
        row[POS_SQ + 3] += qyy
        row[POS_SQ + 4] += qyz
        row[POS_SQ + 5] += qzz
        if K == 4:
            for c, a in enumerate((a01, a02, a03, a11, a12, a13, a22, a23, a33)):
                row[SH_A + c] += a
            for c, a in enumerate((s1r, s1g, s1b, s2r, s2g, s2b, s3r, s3g, s3b)):
                row[SH_B + c] += a
        store_row(row, rows, half, vi, wide_cols, direction, half_cols, half_kind, factor_cols, factor_affine, R_SUM)
    return switches
