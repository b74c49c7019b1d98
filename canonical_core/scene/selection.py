"""Which voxels a decode reads, chosen from the scene's sums: the rows that decode (support above a
floor, not dominated by free space) with the scene's support unit, the strongest of them for a level
of detail, and F_scene of chosen rows. `decoding.SceneDecoding` takes them under the scene's lock;
`mesh` reads the same choice.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch

from ..config import SceneConfig
from .half import from_half

# rows are scanned in this many blocks on the numba threads, each block's results written at its own
# offset and then closed up in block order, so the rows stay ascending whatever the thread count
ROW_BLOCKS = 64


@numba.njit(parallel=True, cache=True)
def _decoded_rows_kernel(r_sum, n_obs, free, min_support, dominance, free_space, keep, support, freeness, ratios):
    n = r_sum.shape[0]
    size = (n + ROW_BLOCKS - 1) // ROW_BLOCKS
    kept, seen = np.zeros(ROW_BLOCKS, np.int64), np.zeros(ROW_BLOCKS, np.int64)
    for b in numba.prange(ROW_BLOCKS):
        start = b * size
        k = s = start
        for v in range(start, min(start + size, n)):
            r = r_sum[v]
            if n_obs[v] > 0:
                ratios[s] = r / np.float32(n_obs[v])
                s += 1
            if r > min_support and (not free_space or free[v] <= dominance * r):
                keep[k], support[k], freeness[k] = v, r, free[v]
                k += 1
        kept[b], seen[b] = k - start, s - start
    total_kept = total_seen = 0
    for b in range(ROW_BLOCKS):  # close up: blocks are disjoint and each moves down, in order
        start = b * size
        for j in range(kept[b]):
            keep[total_kept + j], support[total_kept + j], freeness[total_kept + j] = (
                keep[start + j], support[start + j], freeness[start + j])
        for j in range(seen[b]):
            ratios[total_seen + j] = ratios[start + j]
        total_kept += kept[b]
        total_seen += seen[b]
    return total_kept, total_seen


class DecodedRowSet(NamedTuple):
    """The rows of a scene that decode, with what their opacities need (`decoded_rows`)."""

    rows: np.ndarray  # [K] int64 ascending
    support: torch.Tensor  # [K] float32 R_scene of each
    free: torch.Tensor  # [K] float32 free-space evidence of each
    unit: float  # `decode.support_unit` of the whole scene


def decoded_rows(
    sums: dict[str, np.ndarray],  # a scene's sums, every row
    min_support: float,
    config: SceneConfig,
) -> DecodedRowSet:
    """In one pass over the rows (on the numba threads): those that decode (R_scene > ``min_support``
    and, with free space on, no more see-through evidence than `FreeSpace.dominance` x R_scene:
    voxels that more rays saw through than saw at are not surface), their R_scene and free-space
    evidence, and `decode.support_unit` of the scene (the lower median of R_scene / count, as
    ``torch.median``)."""
    r_sum = sums["r_sum"]  # read where they are (columns of the scene's rows: strided)
    n = r_sum.shape[0]
    keep, ratios = np.empty(n, np.int64), np.empty(n, np.float32)
    support, free = np.empty(n, np.float32), np.empty(n, np.float32)
    kept, seen = _decoded_rows_kernel(
        r_sum, sums["n_obs"], sums["free"], np.float32(min_support), np.float32(config.free_space.dominance),
        config.free_space.enabled, keep, support, free, ratios,
    )  # fmt: skip
    chosen = (keep[:kept], torch.from_numpy(support[:kept]), torch.from_numpy(free[:kept]))
    if not seen:
        return DecodedRowSet(*chosen, 1.0)
    middle = ratios[:seen]
    middle.partition((seen - 1) // 2)  # in place: the scratch is ours
    unit = float(middle[(seen - 1) // 2])
    return DecodedRowSet(*chosen, unit if unit > 1e-6 else 1e-6)


def strongest(
    support: np.ndarray,  # [K] float32
    count: int,
) -> np.ndarray:  # [min(count, K)] int64, ascending
    """The indices of the ``count`` largest values of ``support``, ties going to the lower index, in
    ascending order: the first ``count`` of a stable descending sort, sorted, found in linear time
    (the count-th largest value by partition, then every index above it and the first ones equal
    to it). A picture at a level of detail picks its Gaussians so while the scene's lock is held.

    Example:
        >>> strongest(np.array([0.5, 2.0, 1.0, 2.0, 1.0], np.float32), 3).tolist()
        [1, 2, 3]
    """
    n = support.shape[0]
    if count >= n:
        return np.arange(n)
    if count <= 0:
        return np.zeros(0, np.int64)
    threshold = np.partition(support, n - count)[n - count]
    picked = support > threshold
    picked[np.flatnonzero(support == threshold)[: count - int(picked.sum())]] = True
    return np.flatnonzero(picked)


@numba.njit(parallel=True, cache=True)
def _features_kernel(rows, f_mean, r_sum, eps, out):  # f_mean: [V, L] float16 bits (uint16)
    for i in numba.prange(rows.shape[0]):
        r = r_sum[rows[i]]
        den = r + eps
        for j in range(f_mean.shape[1]):
            out[i, j] = from_half(f_mean[rows[i], j]) * r / den  # the sum as `fields_from_sums` has it, then F_scene


def scene_features(
    sums: dict[str, np.ndarray],  # a scene's sums, every row
    rows: np.ndarray,  # [N] int64
    eps: float,  # `SceneConfig.research.eps`
) -> torch.Tensor:  # [N, L] float32
    """F_scene = sum W F / (R_scene + eps) of ``rows``, as `fields_from_sums` has it (float32, the sum
    being the stored mean times R_scene). The decoded rows do not keep it (it is the largest part of
    a row): cheaper to redo from the sums, read in place (a numba gather: torch's of a strided
    column is several times slower)."""
    f_mean = sums["f_mean"]
    out = np.empty((len(rows), f_mean.shape[1]), np.float32)
    _features_kernel(rows, f_mean.view(np.uint16), sums["r_sum"], np.float32(eps), out)
    return torch.from_numpy(out)
