"""The scene's surface as a signed distance on the voxel lattice, one dense block of cells at a time.

Each occupied voxel keeps the weighted moments of the points lifted into it (`fields`: centroid and
second moments) and, in its SH fit's sums, the weighted sum of the directions it was seen from. Its
tangent plane is the smallest principal axis of those moments pooled over its 3x3x3 neighbourhood
(one voxel's own points are often too few, or all on one depth row, to fix a plane), through its own
centroid, facing the cameras that saw it. The signed distance at a voxel centre is the
support-weighted mean, over the occupied voxels of its 3x3x3 neighbourhood, of its distance to their
tangent planes: positive in front of the surface (the cameras' side), negative behind it, and
defined only within about a voxel of support, the band where marching cubes needs it.

Everything here works on one block's dense cell grid (the caller places each voxel's cell in it), so
memory is bounded by the block's size, not the scene's extent. Units: voxels, block coordinates
(cell ``c`` spans ``[c, c + 1)``, its centre is ``c + 0.5``).
"""

from __future__ import annotations

import numpy as np

from ..config import KEY_BITS, KEY_OFFSET

MARGIN = 2  # cells a block needs around its nodes: a distance reads normals one cell away, which read moments one further
FLAT = 1e-3  # voxels^2: a pooled spread below this in two axes is a line or a point, which fixes no plane

_SQ_COLUMNS = ((0, 1, 2), (1, 3, 4), (2, 4, 5))  # pos_sq's xx xy xz yy yz zz -> rows of the symmetric 3x3


def unpack_cells(keys: np.ndarray) -> np.ndarray:  # [V] int64 packed keys -> [V, 3] int64 lattice cells (i, j, k)
    """The lattice cells of packed voxel keys (`hashing`'s layout: 21 bits per axis, offset)."""
    mask = (1 << KEY_BITS) - 1
    return np.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], -1) - KEY_OFFSET


def view_direction_sums(
    sh_a: np.ndarray,  # [V, K(K+1)/2 - 1] the SH fit's sums of W b b^T (upper triangle without (0, 0))
) -> np.ndarray:  # [V, 3] sum W d, up to a positive factor
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
    sums: dict[str, np.ndarray],  # a scene's sums (`Scene.sums`), rows already chosen
    voxel_size: float,
    eps: float,  # `SceneConfig.research.eps`: the representative's share, as `fields_from_sums` gives it
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # mean [V, 3], second [V, 3, 3], colour [V, 3]
    """Each voxel's centroid and second moment of its lifted points (voxel units, relative to its
    centre) and its fused colour in [0, 1], with `fields_from_sums`'s fallback to the representative
    where R_scene ~ 0."""
    cells = unpack_cells(sums["keys"])
    den = sums["r_sum"].astype(np.float64)[:, None] + eps
    rep = sums["rep_pos"].astype(np.float64) / voxel_size - (cells + 0.5)
    mean = (sums["pos_sum"] + eps * rep) / den
    sq = sums["pos_sq"].astype(np.float64)
    second = np.stack([sq[:, row] for row in _SQ_COLUMNS], 1)
    second = (second + eps * rep[:, :, None] * rep[:, None, :]) / den[:, :, None]
    colour = (sums["rgb_sum"] + eps * sums["rep_rgb"].astype(np.float64) / 255.0) / den
    return mean, second, colour


def box3(a: np.ndarray) -> np.ndarray:  # [X, Y, Z, ...] -> [X, Y, Z, ...]
    """The sum over each cell's 3x3x3 neighbourhood (zero outside the grid), in three separable passes."""
    for axis in range(3):
        lo = (slice(None),) * axis + (slice(None, -1),)
        hi = (slice(None),) * axis + (slice(1, None),)
        out = a.copy()
        out[hi] += a[lo]
        out[lo] += a[hi]
        a = out
    return a


def tangent_planes(
    cells: np.ndarray,  # [N, 3] int64 occupied cells of the block grid
    weight: np.ndarray,  # [N] float64 support of each, > 0
    mean: np.ndarray,  # [N, 3] centroids, block coordinates
    second: np.ndarray,  # [N, 3, 3] second moments E[x x^T], block coordinates
    view: np.ndarray,  # [N, 3] sums of view directions (any positive scale)
    shape: tuple[int, int, int],  # the block grid's cells
) -> np.ndarray:  # [N, 3] unit normals, facing the cameras
    """Each voxel's surface normal: the least-spread axis of the moments pooled over its 3x3x3
    neighbourhood (mixture moments: each voxel's points weighted by its support), turned toward
    the pooled view directions. Where the pooled points fix no plane (`FLAT`), the normal faces the
    cameras straight on."""
    grid = np.zeros(shape + (16,))
    grid[tuple(cells.T)] = np.concatenate([weight[:, None], weight[:, None] * mean,
                                           (weight[:, None, None] * second).reshape(-1, 9), view], 1)
    pooled = box3(grid)[tuple(cells.T)]
    w = pooled[:, :1]
    m = pooled[:, 1:4] / w
    cov = pooled[:, 4:13].reshape(-1, 3, 3) / w[:, :, None] - m[:, :, None] * m[:, None, :]
    spread, axes = np.linalg.eigh(cov)  # ascending: axes[:, :, 0] is the least-spread one
    normal = axes[:, :, 0]
    looking = pooled[:, 13:]
    norm = np.linalg.norm(looking, axis=1, keepdims=True)
    facing = -looking / np.maximum(norm, 1e-30)
    normal = np.where((spread[:, 1] < FLAT)[:, None] & (norm > 0), facing, normal)
    return np.where((np.sum(normal * looking, 1) > 0)[:, None], -normal, normal)


def signed_distance(
    cells: np.ndarray,  # [N, 3] int64 occupied cells of the block grid
    weight: np.ndarray,  # [N] float64 support of each, > 0
    mean: np.ndarray,  # [N, 3] centroids, block coordinates
    normal: np.ndarray,  # [N, 3] unit normals (`tangent_planes`)
    colour: np.ndarray,  # [N, 3] colours in [0, 1]
    shape: tuple[int, int, int],  # the block grid's cells
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # distance [X, Y, Z], defined [X, Y, Z] bool, colour [X, Y, Z, 3]
    """The signed distance (voxels) at every cell centre of the block: the support-weighted mean of
    its distances to the tangent planes of the occupied voxels in its 3x3x3 neighbourhood; defined
    where there is one. The colour at a cell is its own voxel's, or where it holds none the
    neighbourhood's weighted mean (vertices between an occupied and an empty cell take some of it)."""
    w = weight[:, None]
    grid = np.zeros(shape + (8,))
    grid[tuple(cells.T)] = np.concatenate([w, w * normal, w * np.sum(normal * mean, 1, keepdims=True), w * colour], 1)
    near = box3(grid)
    total = near[..., 0]
    defined = total > 0
    safe = np.where(defined, total, 1.0)
    centres = np.stack(np.meshgrid(*(np.arange(n) + 0.5 for n in shape), indexing="ij"), -1)
    distance = (np.sum(centres * near[..., 1:4], -1) - near[..., 4]) / safe
    colours = near[..., 5:] / safe[..., None]
    colours[tuple(cells.T)] = colour
    return distance, defined, colours
