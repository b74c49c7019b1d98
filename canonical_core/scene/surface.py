"""The scene's surface as a signed distance on the voxel lattice (numba kernels).

Each occupied voxel keeps the weighted moments of the points lifted into it (`fields`: centroid and
second moments) and, in its SH fit's sums, the weighted sum of the directions it was seen from. Its
tangent plane: the normal is the least-spread axis of the moments pooled over its 5x5x5
neighbourhood, turned toward the cameras that saw it; the plane passes through the centroid of the
points of its 3x3x3 neighbourhood. Why pooled: one voxel's own points are too few, or all on one
depth row, to fix a plane, and sensor noise spreads one surface's points over a band of voxels a few
deep, where each voxel's own centroid sits at its own depth (planes through them give a bumpy
surface); the wider neighbourhood steadies the normal, the narrower one keeps the plane local. The
signed distance at a voxel centre is the weighted mean, over the occupied voxels of its 3x3x3
neighbourhood, of its distance to their tangent planes: positive in front of the surface (the
cameras' side), negative behind it, and defined only within about a voxel of support, the band
where marching cubes needs it.

Units: voxels. Moments and plane points are relative to each voxel's own centre; the distance is
computed block by block (`block_distance`) on a dense grid of the block's nodes (node j = the centre
of cell origin + j)."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from ..config import KEY_BITS, KEY_OFFSET
from ..decode.eigen import jacobi3, lane_scratch

NORMAL_REACH = 2  # cells each side of a voxel whose moments its normal pools (5x5x5)
FLAT = 1e-3  # voxels^2: a pooled spread below this in two axes is a line or a point, which fixes no plane
_SQ_COLUMNS = ((0, 1, 2), (1, 3, 4), (2, 4, 5))  # pos_sq's xx xy xz yy yz zz -> rows of the symmetric 3x3


def view_direction_sums(
    sh_a: np.ndarray,  # [V, K(K+1)/2 - 1] the SH fit's sums of W b b^T (upper triangle without (0, 0))
) -> np.ndarray:  # [V, 3] float64 sum W d, up to a positive factor
    """The weighted sum of the directions (camera centre to point) each voxel was seen along.

    Why from the SH sums: their first row is sum W Y_0 Y_k(d) for k = 1..3, and the degree-1 basis is
    (-C1 y, C1 z, -C1 x) in 3DGS's order, so the sums already hold sum W d: no extra per-voxel state.
    Needs ``sh_degree >= 1`` (a degree-0 scene keeps no directions).
    """
    if sh_a.shape[1] < 3:
        raise ValueError("sh_degree: a mesh orients its surface by the view directions that sh_degree >= 1 keeps; "
                         "this scene has sh_degree 0")
    return np.stack([-sh_a[:, 2], -sh_a[:, 0], sh_a[:, 1]], -1).astype(np.float64)


def voxel_moments(
    sums: dict[str, np.ndarray],  # float32 sums (`stored.raw_sums` of `Scene.sums`), rows already chosen
    eps: float,  # `SceneConfig.research.eps`: the representative's share, as `fields_from_sums` gives it
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # mean [V, 3], second [V, 3, 3], colour [V, 3]: float64
    """Each voxel's centroid and second moment of its lifted points (voxel units, relative to its
    centre) and its fused colour in [0, 1], with `fields_from_sums`'s fallback to the representative
    where R_scene ~ 0."""
    den = sums["r_sum"].astype(np.float64)[:, None] + eps
    rep = sums["rep_pos"].astype(np.float64)  # local voxel units
    mean = (sums["pos_sum"] + eps * rep) / den
    sq = sums["pos_sq"].astype(np.float64)
    second = np.stack([sq[:, row] for row in _SQ_COLUMNS], 1)
    second = (second + eps * rep[:, :, None] * rep[:, None, :]) / den[:, :, None]
    colour = (sums["rgb_sum"] + eps * sums["rep_rgb"].astype(np.float64) / 255.0) / den
    return mean, second, colour


def pack_cells(cells: np.ndarray) -> np.ndarray:  # [N, 3] int64 -> [N] int64
    """Lattice cells packed as the voxel keys are (`hashing`): one sortable integer per cell."""
    packed = cells + KEY_OFFSET
    return (packed[:, 0] << (2 * KEY_BITS)) | (packed[:, 1] << KEY_BITS) | packed[:, 2]


class Blocks(NamedTuple):
    """Voxels grouped by the cubic blocks of the lattice whose cells (with a margin) hold them."""

    members: np.ndarray  # [M] int64 voxel rows, block after block
    starts: np.ndarray  # [G + 1] int64: block g's members are members[starts[g]:starts[g + 1]]
    origins: np.ndarray  # [G, 3] int64 the first core cell of each block (b * block)


def blocks_of(
    cells: np.ndarray,  # [V, 3] int64 lattice cells
    block: int,  # core cells per block edge (>= 4)
    before: int,  # margin cells below the core a block takes in (<= 2)
    after: int,  # margin cells above it (<= 2)
) -> Blocks:
    """Every block with voxels in its cells ``b * block - before .. (b + 1) * block - 1 + after`` (per
    axis), and those voxels. A cell is in one or two blocks per axis, so in at most eight."""
    first = -((block - 1 + after - cells) // block)  # ceil((cell - block + 1 - after) / block)
    last = (cells + before) // block
    rows, blocks = [], []
    for step in np.ndindex(2, 2, 2):
        b = first + np.array(step)
        inside = np.all(b <= last, 1)
        rows.append(np.flatnonzero(inside))
        blocks.append(b[inside])
    rows, blocks = np.concatenate(rows), np.concatenate(blocks)
    key = pack_cells(blocks)
    order = np.argsort(key, kind="stable")
    key = key[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    return Blocks(rows[order], np.r_[starts, len(order)].astype(np.int64), blocks[order][starts] * block)


@numba.njit(parallel=True, cache=True)
def _tangent_planes_kernel(members, starts, origins, cells, block, weight, mean, second, view, flat, reach, normal, point):
    side = block + 2 * reach
    for g in numba.prange(starts.shape[0] - 1):
        # the block's cells and margin as a dense grid of voxel rows: neighbours by index, in cache
        grid = np.full((side, side, side), -1, np.int64)
        o0, o1, o2 = origins[g, 0] - reach, origins[g, 1] - reach, origins[g, 2] - reach
        for t in range(starts[g], starts[g + 1]):
            u = members[t]
            grid[cells[u, 0] - o0, cells[u, 1] - o1, cells[u, 2] - o2] = u
        count = starts[g + 1] - starts[g]
        a = np.empty((count, 3, 3))  # the pooled covariances, diagonalised in place together
        vec = np.empty((count, 3, 3))
        looks = np.empty((count, 3))  # the pooled view directions
        inner = np.empty(count, np.int64)  # the block's own voxels (not its margin's)
        k = 0
        for t in range(starts[g], starts[g + 1]):
            v = members[t]
            x, y, z = cells[v, 0] - o0, cells[v, 1] - o1, cells[v, 2] - o2
            if min(x, y, z) < reach or max(x, y, z) >= reach + block:
                continue  # a margin voxel: its own block does it
            w = m0 = m1 = m2 = l0 = l1 = l2 = 0.0
            pw = p0 = p1 = p2 = 0.0
            s = a[k]
            s[:] = 0.0
            for dx in range(-reach, reach + 1):
                for dy in range(-reach, reach + 1):
                    for dz in range(-reach, reach + 1):
                        u = grid[x + dx, y + dy, z + dz]
                        if u < 0:
                            continue
                        wu = weight[u]
                        d0, d1, d2 = dx + mean[u, 0], dy + mean[u, 1], dz + mean[u, 2]
                        w += wu
                        m0, m1, m2 = m0 + wu * d0, m1 + wu * d1, m2 + wu * d2
                        c = (float(dx), float(dy), float(dz))
                        for i in range(3):  # E[x x^T] of the neighbour's points, moved by its offset
                            for j in range(3):
                                s[i, j] += wu * (second[u, i, j] + c[i] * mean[u, j] + mean[u, i] * c[j] + c[i] * c[j])
                        l0, l1, l2 = l0 + view[u, 0], l1 + view[u, 1], l2 + view[u, 2]
                        if abs(dx) <= 1 and abs(dy) <= 1 and abs(dz) <= 1:  # the plane's point: 3x3x3
                            pw, p0, p1, p2 = pw + wu, p0 + wu * d0, p1 + wu * d1, p2 + wu * d2
            mm = (m0 / w, m1 / w, m2 / w)
            for i in range(3):
                for j in range(3):
                    s[i, j] = s[i, j] / w - mm[i] * mm[j]
            looks[k, 0], looks[k, 1], looks[k, 2] = l0, l1, l2
            point[v, 0], point[v, 1], point[v, 2] = p0 / pw, p1 / pw, p2 / pw
            inner[k] = v
            k += 1
        jacobi3(a, vec, 0, k, lane_scratch())  # the block's covariances together (in vector lanes)
        for q in range(k):
            v = inner[q]
            l0, l1, l2 = looks[q, 0], looks[q, 1], looks[q, 2]
            d = (a[q, 0, 0], a[q, 1, 1], a[q, 2, 2])
            low = 0 if d[0] <= d[1] and d[0] <= d[2] else (1 if d[1] <= d[2] else 2)
            middle = max(min(d[(low + 1) % 3], d[(low + 2) % 3]), 0.0)
            n0, n1, n2 = vec[q, 0, low], vec[q, 1, low], vec[q, 2, low]
            look = np.sqrt(l0 * l0 + l1 * l1 + l2 * l2)
            if middle < flat and look > 0.0:  # no plane: face the cameras straight on
                n0, n1, n2 = -l0 / look, -l1 / look, -l2 / look
            sign = -1.0 if n0 * l0 + n1 * l1 + n2 * l2 > 0.0 else 1.0
            normal[v, 0], normal[v, 1], normal[v, 2] = sign * n0, sign * n1, sign * n2


def tangent_planes(
    cells: np.ndarray,  # [N, 3] int64 the occupied voxels' lattice cells
    weight: np.ndarray,  # [N] float64 each voxel's points' total weight (R_scene), > 0
    mean: np.ndarray,  # [N, 3] float64 centroids (voxel units, relative to each voxel's centre)
    second: np.ndarray,  # [N, 3, 3] float64 second moments, likewise
    view: np.ndarray,  # [N, 3] float64 sums of view directions (any positive scale)
    block: int = 32,  # cells per block edge of the work (it changes nothing but the cost)
) -> tuple[np.ndarray, np.ndarray]:  # normal [N, 3] unit, facing the cameras; point [N, 3] on the plane
    """Each voxel's tangent plane (module docstring): the normal, the least-spread axis of the moments
    pooled over `NORMAL_REACH` cells each side (mixture moments: each voxel's points weighted by
    ``weight``), turned toward the pooled view directions; where those points fix no plane (`FLAT`)
    it faces the cameras straight on. The point: the weighted centroid of the 3x3x3 neighbourhood's
    points, in the voxel's own units. Worked block by block, each on a dense grid of its cells."""
    normal, point = np.empty((len(cells), 3)), np.empty((len(cells), 3))
    if len(cells):
        groups = blocks_of(cells, block, NORMAL_REACH, NORMAL_REACH)
        _tangent_planes_kernel(groups.members, groups.starts, groups.origins, cells, block, weight, mean, second, view,
                               FLAT, NORMAL_REACH, normal, point)
    return normal, point


@numba.njit(cache=True)
def _block_distance_kernel(members, cells, origin, weight, point, normal, colour, num, den, col, own):
    size = num.shape[0]
    for t in range(members.shape[0]):
        u = members[t]
        wu = weight[u]
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    i, j, k = cells[u, 0] + dx - origin[0], cells[u, 1] + dy - origin[1], cells[u, 2] + dz - origin[2]
                    if i < 0 or j < 0 or k < 0 or i >= size or j >= size or k >= size:
                        continue
                    # the node's distance to u's plane: its centre minus the plane's point, along u's normal
                    dist = normal[u, 0] * (dx - point[u, 0]) + normal[u, 1] * (dy - point[u, 1]) + normal[u, 2] * (dz - point[u, 2])
                    num[i, j, k] += wu * dist
                    den[i, j, k] += wu
                    for c in range(3):
                        col[i, j, k, c] += wu * colour[u, c]
                    if dx == 0 and dy == 0 and dz == 0:
                        own[i, j, k] = u


def block_distance(
    members: np.ndarray,  # [M] int64 the voxels within one cell of the block's nodes
    cells: np.ndarray,  # [N, 3] int64 lattice cells of all voxels
    origin: np.ndarray,  # [3] int64 the cell of the block's node 0
    size: int,  # nodes per block edge
    weight: np.ndarray,  # [N] float64 (as `tangent_planes`')
    point: np.ndarray,  # [N, 3] float64 a point of each plane, relative to its voxel's centre (`tangent_planes`)
    normal: np.ndarray,  # [N, 3] float64 (`tangent_planes`)
    colour: np.ndarray,  # [N, 3] float64 in [0, 1]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # distance [S, S, S], defined [S, S, S] bool, colour [S, S, S, 3]
    """The signed distance (voxels) at the block's nodes: the weighted mean of each node's
    distances to the tangent planes of the occupied voxels in its 3x3x3 neighbourhood; defined where
    there is one. A node's colour is its own voxel's, or where it holds none the neighbourhood's
    weighted mean (a vertex between an occupied and an empty node takes some of it)."""
    num, den = np.zeros((size,) * 3), np.zeros((size,) * 3)
    col = np.zeros((size,) * 3 + (3,))
    own = np.full((size,) * 3, -1, np.int64)
    _block_distance_kernel(members, cells, origin, weight, point, normal, colour, num, den, col, own)
    defined = den > 0
    safe = np.where(defined, den, 1.0)
    colours = col / safe[..., None]
    mine = own >= 0
    colours[mine] = colour[own[mine]]
    return num / safe, defined, colours
