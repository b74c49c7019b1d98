"""Free-space evidence: what each frame saw *through*, folded into the scene as negative evidence.

Each frame is reduced to a coarse see-through map: per cell of ``cell x cell`` pixels, the nearest
valid depth d_min (conservative at holes and depth edges) and the threshold
``d_min - (margin * voxel + sigmas * sigma(d_min))`` in front of which a voxel centre is seen through
(sigma from the frame's depth std or the sensor noise model, so noisier depth carves less). A voxel
whose centre projects into a cell in front of its threshold gains

    w = exp(-sigma / voxel) * valid_fraction(cell) * fx * fy * voxel^2 / z^2

i.e. the reliability of the rays times the number of valid rays that pass through the voxel, which
is the unit of R_scene (reliability-weighted pixel observations), so the two can be compared. The
ablations that treat reliability as 1 (``no_reliability``, ``average``) count rays unweighted
here too, so support and free-space evidence stay in one unit.

Order independence: voxel centres are fixed, so the test of (voxel, frame) never changes. A fold
tests every voxel in the frame's frustum, including the voxels it creates (chunk AABBs cull the
rest, so the cost is bounded by the chunks the frustum meets), and tests the voxels it creates
against a bounded history of earlier frames' maps. With the history holding all frames, every voxel
ends with the same sum whatever the frame order (up to float summation order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..config import KEY_BITS, KEY_OFFSET, SceneConfig

CHUNK = 1024  # voxels per chunk of the insertion-ordered state; each chunk keeps its voxel AABB
_BLOCK = 256  # voxels a history-kernel task tests against every kept map
_MASK = (1 << KEY_BITS) - 1


@dataclass
class SeeThroughMap:
    """A frame's coarse see-through map and the coarse camera that indexes it."""

    threshold: np.ndarray  # [h, w] float32: depth in front of which a voxel is seen through (0 = no data)
    weight: np.ndarray  # [h, w] float32: exp(-sigma / voxel) * valid fraction of the cell
    w2c: np.ndarray  # [3, 4] float32 world-to-camera
    intrinsics: np.ndarray  # [4] float32 coarse fx, fy, cx, cy
    area_scale: float  # full-resolution fx * fy * voxel^2


@numba.njit(inline="always")
def _std_of_first(depth, std, v0, v1, u0, u1, d):
    """std of the first pixel of the cell [v0, v1) x [u0, u1), in row-major order, whose depth is d."""
    for v in range(v0, v1):
        for u in range(u0, u1):
            if depth[v, u] == d:
                return std[v, u]
    return np.float32(0.0)


@numba.njit(parallel=True, cache=True)
def _coarse_map_kernel(depth, std, has_std, cell, near, far, sigma0, sigma2, z_ref, voxel, margin, sigmas, weighted, thr, wcell):
    H, W = depth.shape
    h, w = thr.shape
    inf = np.float32(np.inf)
    for cy in numba.prange(h):
        v0, v1 = cy * cell, min((cy + 1) * cell, H)
        # per pixel column of this cell row: nearest valid depth and valid count (elementwise, vectorised)
        col_min = np.full(W, inf, np.float32)
        col_n = np.zeros(W, np.int32)
        for v in range(v0, v1):
            for u in range(W):
                z = depth[v, u]
                valid = (z > near) & (z < far)
                col_min[u] = min(col_min[u], z) if valid else col_min[u]
                col_n[u] += np.int32(1) if valid else np.int32(0)
        for cx in range(w):
            u0, u1 = cx * cell, min((cx + 1) * cell, W)
            dmin, n = inf, 0
            for u in range(u0, u1):
                dmin = min(dmin, col_min[u])
                n += col_n[u]
            if n == 0:
                thr[cy, cx] = 0.0
                wcell[cy, cx] = 0.0
                continue
            if has_std:
                smin = _std_of_first(depth, std, v0, v1, u0, u1, dmin)
            else:
                smin = sigma0 + sigma2 * (dmin - z_ref) * (dmin - z_ref)
            thr[cy, cx] = dmin - (margin * voxel + sigmas * smin)
            wcell[cy, cx] = (np.exp(-smin / voxel) if weighted else np.float32(1.0)) * n / (cell * cell)


def see_through_map(frame, config: SceneConfig) -> SeeThroughMap:
    """The coarse see-through map of a frame with depth (see module docstring)."""
    c = config.free_space.cell
    H, W = frame.height, frame.width
    h, w = -(-H // c), -(-W // c)
    thr = np.empty((h, w), np.float32)
    wcell = np.empty((h, w), np.float32)
    std = frame.depth_std.numpy() if frame.depth_std is not None else np.zeros((1, 1), np.float32)
    sensor = config.sensor.in_effect(frame.depth.numpy())  # a scene's own choice; outside one, this frame's family
    _coarse_map_kernel(frame.depth.numpy(), std, frame.depth_std is not None, c, np.float32(config.range.near),
                       np.float32(config.range.far), np.float32(sensor.sigma0), np.float32(sensor.sigma2),
                       np.float32(sensor.sigma_ref), np.float32(config.voxel_size),
                       np.float32(config.free_space.margin), np.float32(config.free_space.sigmas),
                       config.uses_reliability, thr, wcell)
    cam = frame.camera
    coarse = np.array([cam.fx / c, cam.fy / c, (cam.cx + 0.5) / c - 0.5, (cam.cy + 0.5) / c - 0.5], np.float32)
    w2c = np.linalg.inv(cam.c2w64())[:3].astype(np.float32)
    return SeeThroughMap(thr, wcell, w2c, coarse, float(cam.fx * cam.fy * config.voxel_size**2))


@numba.njit(inline="always")
def _project_block(keys, start, n, voxel, P, intr, e, h, w, near, iu, iv, zc):
    """Cell (iu, iv) of map ``e`` (camera P[e], intr[e], [h, w] cells) under each voxel centre of
    keys[start:start + n], iv = -1 where the centre is behind the near plane or outside the map, and
    the centre's camera depth zc. Branch-free, so the compiler vectorises it."""
    p00, p01, p02, p03 = P[e, 0, 0], P[e, 0, 1], P[e, 0, 2], P[e, 0, 3]
    p10, p11, p12, p13 = P[e, 1, 0], P[e, 1, 1], P[e, 1, 2], P[e, 1, 3]
    p20, p21, p22, p23 = P[e, 2, 0], P[e, 2, 1], P[e, 2, 2], P[e, 2, 3]
    fx, fy, cx, cy = intr[e, 0], intr[e, 1], intr[e, 2], intr[e, 3]
    half, fw, fh = np.float32(0.5), np.float32(w), np.float32(h)
    for t in range(n):
        key = keys[start + t]
        # voxel centre; the index fits in int32, whose conversion to float vectorises
        x = (np.float32(np.int32(((key >> (2 * KEY_BITS)) & _MASK) - KEY_OFFSET)) + half) * voxel
        y = (np.float32(np.int32(((key >> KEY_BITS) & _MASK) - KEY_OFFSET)) + half) * voxel
        z = (np.float32(np.int32((key & _MASK) - KEY_OFFSET)) + half) * voxel
        xc = p00 * x + p01 * y + p02 * z + p03
        yc = p10 * x + p11 * y + p12 * z + p13
        zt = p20 * x + p21 * y + p22 * z + p23
        zs = zt if zt > near else np.float32(1.0)  # no division by ~0 behind the camera (masked anyway)
        u = fx * xc / zs + cx + half
        v = fy * yc / zs + cy + half
        inside = (zt > near) & (u >= 0) & (v >= 0) & (u < fw) & (v < fh)  # floor(u) in [0, w) iff u in [0, w)
        iu[t] = np.int32(np.floor(u)) if inside else np.int32(0)
        iv[t] = np.int32(np.floor(v)) if inside else np.int32(-1)
        zc[t] = zt


@numba.njit(inline="always")
def _see_through(thr, wcell, e, iu, iv, zc, area_scale):
    """Evidence of map ``e`` that a centre at depth zc in its cell (iu, iv) is seen through."""
    r = max(iv, 0)
    t = thr[e, r, iu]
    seen = (iv >= 0) & (t > np.float32(0.0)) & (zc < t)  # iv >= 0 implies zc > near > 0
    z2 = zc * zc if seen else np.float32(1.0)
    return wcell[e, r, iu] * area_scale / z2 if seen else np.float32(0.0)


@numba.njit(inline="always")
def _box_outside_frustum(lo, hi, voxel, P, intr, h, w, near):
    """True when all 8 corners of the voxel box [lo, hi + 1) * voxel lie outside one frustum plane."""
    out = np.zeros(5, np.int64)
    for corner in range(8):
        x = (lo[0] if corner & 1 == 0 else hi[0] + 1) * voxel
        y = (lo[1] if corner & 2 == 0 else hi[1] + 1) * voxel
        z = (lo[2] if corner & 4 == 0 else hi[2] + 1) * voxel
        xc = P[0, 0] * x + P[0, 1] * y + P[0, 2] * z + P[0, 3]
        yc = P[1, 0] * x + P[1, 1] * y + P[1, 2] * z + P[1, 3]
        zc = P[2, 0] * x + P[2, 1] * y + P[2, 2] * z + P[2, 3]
        out[0] += zc < near
        out[1] += intr[0] * xc + (intr[2] + 0.5) * zc < 0  # left of u = -0.5
        out[2] += intr[0] * xc + (intr[2] + 0.5 - w) * zc > 0  # right of u = w - 0.5
        out[3] += intr[1] * yc + (intr[3] + 0.5) * zc < 0
        out[4] += intr[1] * yc + (intr[3] + 0.5 - h) * zc > 0
    for p in range(5):
        if out[p] == 8:
            return True
    return False


@numba.njit(parallel=True, cache=True)
def frustum_chunks_kernel(chunk_lo, chunk_hi, n_voxels, voxel, P, intr, h, w, near, out):
    """The chunks of voxels [0, n_voxels) whose boxes the frustum (camera P, coarse ``intr``, an
    [h, w] map) meets, ascending, into ``out``; returns how many."""
    n_chunks = (n_voxels + CHUNK - 1) // CHUNK
    meets = np.empty(n_chunks, np.bool_)
    for ch in numba.prange(n_chunks):
        meets[ch] = not _box_outside_frustum(chunk_lo[ch], chunk_hi[ch], voxel, P, intr, h, w, near)
    count = 0
    for ch in range(n_chunks):
        if meets[ch]:
            out[count] = ch
            count += 1
    return count


def frustum_chunks(voxels, m: SeeThroughMap, config: SceneConfig) -> np.ndarray:  # voxels: a VoxelMap
    """[C] int32: the chunks of ``voxels`` that the frustum of map ``m`` meets (the free-space pass
    tests their voxels and no others)."""
    n = len(voxels)
    out = np.empty((n + CHUNK - 1) // CHUNK, np.int32)
    h, w = m.threshold.shape
    count = frustum_chunks_kernel(voxels.chunk_lo, voxels.chunk_hi, n, np.float32(config.voxel_size), m.w2c,
                                  m.intrinsics, h, w, np.float32(config.range.near), out)
    return out[:count]


@numba.njit(parallel=True, cache=True)
def frame_free_space_kernel(keys, free, chunks, n_voxels, voxel, P, intr, thr, wcell, area_scale, near):
    """Add one frame's see-through evidence to every voxel of ``chunks`` (those its frustum meets)."""
    h, w = thr.shape
    # the frame's map as map 0 of a stack of one
    P1, intr1, thr1, wcell1 = P.reshape(1, 3, 4), intr.reshape(1, 4), thr.reshape(1, h, w), wcell.reshape(1, h, w)
    for c in numba.prange(chunks.shape[0]):
        start = chunks[c] * CHUNK
        n = min(CHUNK, n_voxels - start)
        iu, iv, zc = np.empty(CHUNK, np.int32), np.empty(CHUNK, np.int32), np.empty(CHUNK, np.float32)
        _project_block(keys, start, n, voxel, P1, intr1, 0, h, w, near, iu, iv, zc)
        for t in range(n):
            free[start + t] += _see_through(thr1, wcell1, 0, iu[t], iv[t], zc[t], area_scale)


@numba.njit(inline="always")
def _voxel_index(key):
    """The voxel index (i, j, k) a key packs."""
    return (((key >> (2 * KEY_BITS)) & _MASK) - KEY_OFFSET, ((key >> KEY_BITS) & _MASK) - KEY_OFFSET,
            (key & _MASK) - KEY_OFFSET)


@numba.njit(inline="always")
def _block_box(keys, start, n):
    """Voxel-index box (lo, hi: [3] int64, both inclusive) of the voxels keys[start:start + n], n >= 1."""
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for t in range(n):
        ijk = _voxel_index(keys[start + t])
        for a in range(3):
            if t == 0 or ijk[a] < lo[a]:
                lo[a] = ijk[a]
            if t == 0 or ijk[a] > hi[a]:
                hi[a] = ijk[a]
    return lo, hi


@numba.njit(parallel=True, cache=True)
def history_free_space_kernel(keys, free, first, last, voxel, order, P, intr, thr, wcell, dims, area, near):
    """Add the evidence of earlier frames (history entries ``order``, oldest first) to voxels [first, last)."""
    for blk in numba.prange((last - first + _BLOCK - 1) // _BLOCK):
        start = first + blk * _BLOCK
        n = min(_BLOCK, last - start)
        iu, iv, zc = np.empty(_BLOCK, np.int32), np.empty(_BLOCK, np.int32), np.empty(_BLOCK, np.float32)
        acc = free[start:start + n].copy()
        lo, hi = _block_box(keys, start, n)
        for e in order:  # oldest first, so each voxel sums in the same order as a per-voxel loop
            if _box_outside_frustum(lo, hi, voxel, P[e], intr[e], dims[e, 0], dims[e, 1], near):
                continue  # no centre of the block projects into map e: it would add 0 to each
            _project_block(keys, start, n, voxel, P, intr, e, dims[e, 0], dims[e, 1], near, iu, iv, zc)
            for t in range(n):
                acc[t] += _see_through(thr, wcell, e, iu[t], iv[t], zc[t], area[e])
        free[start:start + n] = acc


@numba.njit(cache=True)
def update_chunk_boxes_kernel(keys, first, last, chunk_lo, chunk_hi):
    """Grow the voxel-index AABBs of the chunks holding voxels [first, last)."""
    for vi in range(first, last):
        ch = vi // CHUNK
        ijk = _voxel_index(keys[vi])
        for a in range(3):
            if vi % CHUNK == 0 or ijk[a] < chunk_lo[ch, a]:
                chunk_lo[ch, a] = ijk[a]
            if vi % CHUNK == 0 or ijk[a] > chunk_hi[ch, a]:
                chunk_hi[ch, a] = ijk[a]


class SeeThroughHistory:
    """A ring buffer of the last ``capacity`` frames' see-through maps (for voxels created later)."""

    def __init__(self, capacity: int, shape: tuple[int, int] = (1, 1)):
        self.capacity = capacity
        self.count = 0
        self.head = 0  # next slot to write
        h, w = shape
        self.threshold = np.zeros((capacity, h, w), np.float32)
        self.weight = np.zeros((capacity, h, w), np.float32)
        self.w2c = np.zeros((capacity, 3, 4), np.float32)
        self.intrinsics = np.zeros((capacity, 4), np.float32)
        self.dims = np.zeros((capacity, 2), np.int64)
        self.area = np.zeros(capacity, np.float32)

    def order(self) -> np.ndarray:  # [count] slot indices, oldest first
        return (self.head - self.count + np.arange(self.count)) % self.capacity

    def push(self, m: SeeThroughMap) -> None:
        h, w = m.threshold.shape
        if h > self.threshold.shape[1] or w > self.threshold.shape[2]:  # a larger frame: widen the maps
            for name in ("threshold", "weight"):
                old = getattr(self, name)
                new = np.zeros((self.capacity, max(h, old.shape[1]), max(w, old.shape[2])), np.float32)
                new[:, : old.shape[1], : old.shape[2]] = old
                setattr(self, name, new)
        s = self.head
        self.threshold[s, :h, :w], self.weight[s, :h, :w] = m.threshold, m.weight
        self.w2c[s], self.intrinsics[s], self.dims[s], self.area[s] = m.w2c, m.intrinsics, (h, w), m.area_scale
        self.head = (self.head + 1) % self.capacity
        self.count = min(self.count + 1, self.capacity)

    _ARRAYS = ("threshold", "weight", "w2c", "intrinsics", "dims", "area")

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self._ARRAYS} | {"ring": np.array([self.count, self.head], np.int64)}

    @classmethod
    def from_arrays(cls, capacity: int, arrays: dict[str, np.ndarray]) -> "SeeThroughHistory":
        hist = cls(capacity)
        for name in cls._ARRAYS:
            setattr(hist, name, np.array(arrays[name]))
        hist.count, hist.head = (int(x) for x in arrays["ring"])
        return hist
