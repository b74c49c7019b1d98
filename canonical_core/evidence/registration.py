"""Colour next to depth edges: evidence whose colour may belong to the surface on the other side.

Most RGB-D cameras measure colour and depth with two sensors, and the calibration that maps depth
into the colour image is off by a few pixels (10-20 on a Kinect v1, at edges). Inside a surface that
shifts colour by a little; at a depth discontinuity it paints the background's colour onto the
foreground's rim (and back), and each view paints a different rim. Near such an edge the lifted
point is right but its colour is not trustworthy, so the evidence there is down-weighted:

    w(m) = min(1, (d(m) + 1) / (r + 1))

where d(m) is the chessboard distance in pixels from pixel m to the nearest depth edge and r the
registration radius. A voxel seen near an edge in one view and well inside a surface in another
takes its colour (and its other fields) from the latter; a voxel only ever seen near edges keeps
its evidence, scaled. r = 0 gives w = 1 everywhere.

A depth edge is a pixel with valid depth whose largest jump to a valid 8-neighbour exceeds
``2 voxel_size + 3 sigma(z)``: a jump a surface of the map cannot make within two voxels, beyond
the sensor's noise at that depth.

r is the sensor's, declared by the session (`SceneConfig.sensor.registration_px`). It is not
estimated from the frames: the mean colour gradient around a real capture's depth edges (RealSense,
HoloLens) shows no peak that locates the colour edge, unlike a registered synthetic capture's.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from .reliability import edge_jump, sensor_depth_std


@numba.njit(parallel=True, cache=True)
def _edge_mask_kernel(depth, voxel, sigma0, sigma2, z_ref, out):
    H, W = depth.shape
    for v in numba.prange(H):
        for u in range(W):
            z = depth[v, u]
            out[v, u] = False
            if z <= 0:
                continue
            jump = edge_jump(depth, v, u)
            sigma = sigma0 + sigma2 * (z - z_ref) * (z - z_ref)
            out[v, u] = jump > 2 * voxel + 3 * sigma


def depth_edges(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    voxel_size: float,
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
) -> np.ndarray:  # [H, W] bool
    """Pixels on a depth discontinuity (see the module's rule; the noise model as `sensor_depth_std`)."""
    if depth.ndim != 2:
        raise ValueError(f"depth: expected shape [H, W], got {list(depth.shape)}")
    out = np.empty(depth.shape, np.bool_)
    _edge_mask_kernel(np.ascontiguousarray(depth, np.float32), np.float32(voxel_size), np.float32(sigma0),
                      np.float32(sigma2), np.float32(z_ref), out)
    return out


@numba.njit(parallel=True, cache=True)
def _edge_distance_kernel(edges, cap, rowdist, out):
    # chessboard distance is separable: the nearest edge in each row, then the best row within cap
    H, W = edges.shape
    for v in numba.prange(H):
        last = -(1 << 30)
        for u in range(W):
            if edges[v, u]:
                last = u
            rowdist[v, u] = min(u - last, cap)
        last = 1 << 30
        for u in range(W - 1, -1, -1):
            if edges[v, u]:
                last = u
            rowdist[v, u] = min(rowdist[v, u], last - u)
    for v in numba.prange(H):
        for u in range(W):
            best = cap
            for dv in range(-min(cap, v), min(cap, H - 1 - v) + 1):
                best = min(best, max(abs(dv), rowdist[v + dv, u]))
            out[v, u] = best


def edge_distance(
    edges: np.ndarray,  # [H, W] bool
    cap: int,
) -> np.ndarray:  # [H, W] int32, min(cap, chessboard distance to the nearest True pixel)
    """Chessboard distance in pixels to the nearest edge pixel, capped at ``cap`` (numba;
    `registration_weight_reference` is the definition by repeated 3x3 dilation)."""
    out = np.empty(edges.shape, np.int32)
    _edge_distance_kernel(np.ascontiguousarray(edges), np.int32(cap), np.empty(edges.shape, np.int32), out)
    return out


def registration_weight(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    rows: np.ndarray,  # [M] pixel rows of the observations
    cols: np.ndarray,  # [M] pixel columns
    radius_px: float,
    voxel_size: float,
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
) -> np.ndarray:  # [M] float32 in (0, 1]
    """w = min(1, (d + 1) / (radius_px + 1)) at the given pixels, d the distance to the nearest depth edge.

    Example:
        >>> depth = np.full((5, 9), 1.0, np.float32); depth[:, 5:] = 2.0  # a step between columns 4 and 5
        >>> rows, cols = np.zeros(9, np.int64), np.arange(9)
        >>> [round(float(w), 2) for w in registration_weight(depth, rows, cols, 2.0, 0.01)]
        [1.0, 1.0, 1.0, 0.67, 0.33, 0.33, 0.67, 1.0, 1.0]
    """
    if not radius_px > 0:
        return np.ones(rows.shape[0], np.float32)
    cap = int(np.ceil(radius_px))
    d = edge_distance(depth_edges(depth, voxel_size, sigma0, sigma2, z_ref), cap)[rows, cols]
    return np.minimum(np.float32(1.0), (d + np.float32(1.0)) / np.float32(radius_px + 1.0)).astype(np.float32)


def registration_weight_reference(
    depth: Tensor,  # [H, W] float32 metres, 0 = missing
    radius_px: float,
    voxel_size: float,
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
) -> Tensor:  # [H, W] float32, the weight of every pixel (meaningful where depth > 0)
    """Whole-image PyTorch definition of `registration_weight`: edges by the jump rule, distances by
    dilating the edge mask one 3x3 step at a time."""
    H, W = depth.shape
    if radius_px <= 0:
        return torch.ones((H, W))
    padded = torch.nn.functional.pad(depth[None, None], (1, 1, 1, 1))[0, 0]
    jump = torch.zeros_like(depth)
    for dv in range(3):
        for du in range(3):
            zn = padded[dv: dv + H, du: du + W]
            jump = torch.maximum(jump, torch.where((zn > 0) & (depth > 0), (zn - depth).abs(), torch.zeros_like(depth)))
    edges = (depth > 0) & (jump > 2 * voxel_size + 3 * sensor_depth_std(depth, sigma0, sigma2, z_ref))
    cap = int(np.ceil(radius_px))
    distance = torch.full((H, W), float(cap))
    reached = edges.clone()
    for step in range(cap):
        distance = torch.where(reached & (distance > step), torch.full_like(distance, float(step)), distance)
        reached = torch.nn.functional.max_pool2d(reached[None, None].float(), 3, 1, 1)[0, 0] > 0
    return torch.clamp((distance + 1.0) / (radius_px + 1.0), max=1.0)

