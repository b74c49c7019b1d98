"""Mixed ("flying") depth pixels: pixels on a depth discontinuity, whose depth and colour may be a
blend of the foreground and the background.

Structured-light and time-of-flight sensors return, along every depth edge, pixels whose depth lies
between the two surfaces (the sensor's footprint straddles both) and whose colour is the
background's or the foreground's depending on the colour camera's registration. Folded, they make
voxels in the empty space in front of the background and paint the background's colour on the
foreground's rim: the halos around chairs and partitions. Other views see those surfaces away from
the edge, so such a pixel is dropped before it makes voxels rather than down-weighted (a voxel that
only rim pixels ever saw would keep their colour, however small its weight).

Two rules (`MixedRule`):
- ``jump``: the largest jump to a valid 8-neighbour exceeds ``threshold`` x the pixel's depth (both
  sides of every edge go);
- ``between``: the depth lies strictly between two opposite neighbours (left-right, up-down or a
  diagonal pair) that each differ from it by more than ``threshold`` x its depth (only the blended
  pixels go; the foreground's and the background's own rims stay).
"""

from __future__ import annotations

import numba
import numpy as np

from ..config import MixedRule
from .reliability import edge_jump

_RULES = {"jump": 0, "between": 1}


@numba.njit(inline="always")
def _between(depth, v, u, threshold):
    H, W = depth.shape
    z = depth[v, u]
    gap = threshold * z
    for dv, du in ((0, 1), (1, 0), (1, 1), (1, -1)):  # the four pairs of opposite neighbours
        va, ua, vb, ub = v - dv, u - du, v + dv, u + du
        if not (0 <= va < H and 0 <= vb < H and 0 <= ua < W and 0 <= ub < W):
            continue
        za, zb = depth[va, ua], depth[vb, ub]
        if za > 0 and zb > 0 and min(za, zb) < z - gap and max(za, zb) > z + gap:
            return True
    return False


@numba.njit(parallel=True, cache=True)
def _mixed_kernel(depth, rows, cols, threshold, rule, out):
    for i in numba.prange(rows.shape[0]):
        v, u = rows[i], cols[i]
        if rule == 0:
            out[i] = edge_jump(depth, v, u) > threshold * depth[v, u]
        else:
            out[i] = _between(depth, v, u, threshold)


def mixed_pixels(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    rows: np.ndarray,  # [M] int64 pixel rows (valid depth)
    cols: np.ndarray,  # [M] int64 pixel columns
    threshold: float,
    rule: MixedRule = "jump",
) -> np.ndarray:  # [M] bool: True where the pixel is mixed
    """Which of the given pixels are mixed by ``rule`` (module docstring), the depth jump measured
    relative to the pixel's depth (``threshold`` 0.05: 5 %).

    Example:
        >>> depth = np.array([[1.0, 1.0, 1.5, 2.0, 2.0]], np.float32)  # 1.5: a pixel between two surfaces
        >>> rows, cols = np.zeros(5, np.int64), np.arange(5)
        >>> mixed_pixels(depth, rows, cols, 0.05, "between").tolist()
        [False, False, True, False, False]
        >>> mixed_pixels(depth, rows, cols, 0.05, "jump").tolist()
        [False, True, True, True, False]
    """
    if rule not in _RULES:
        raise ValueError(f"rule: expected one of {list(_RULES)}, got {rule!r}")
    if not threshold > 0:
        raise ValueError(f"threshold: expected a positive relative jump, got {threshold!r}")
    out = np.empty(rows.shape[0], np.bool_)
    _mixed_kernel(np.ascontiguousarray(depth, np.float32), rows.astype(np.int64, copy=False), cols.astype(np.int64, copy=False),
                  np.float32(threshold), _RULES[rule], out)
    return out
