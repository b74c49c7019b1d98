"""Positional and appearance uncertainty, and the reliability R_view = exp(-U_pos) * exp(-U_app).

U_pos is measured in units of the scene's voxel size, so reliability does not depend on the
scene's unit. With supplied depth it comes from the client's per-pixel std, or from a sensor noise
model sigma(z) = sigma0 + sigma2 * (z - z_ref)^2; in both cases a depth-edge term
``edge_weight * max |z - z_neighbour|`` over valid 8-neighbours is added, because pixels on depth
discontinuities ("flying pixels") are the main source of floaters and no per-pixel std reports them.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor, nn


def sensor_depth_std(
    depth: np.ndarray | Tensor,  # [H, W] metres (any shape)
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
) -> np.ndarray | Tensor:  # same shape and kind, metres
    """The sensor noise model sigma(z) = sigma0 + sigma2 * (z - z_ref)^2 (used where a frame's depth
    comes without a per-pixel std).

    Example:
        >>> round(float(sensor_depth_std(np.float32(1.4))), 4)
        0.0031
    """
    return sigma0 + sigma2 * (depth - z_ref) ** 2


@numba.njit(inline="always")
def edge_jump(depth, v, u):
    """The largest |z_neighbour - z| of pixel (v, u) over its valid 8-neighbours (0 if none): the
    depth-edge measure of U_pos and of the registration's edge mask."""
    H, W = depth.shape
    z = depth[v, u]
    jump = np.float32(0.0)
    # missing neighbours (0) say nothing about an edge (a select, not a branch)
    if 0 < v < H - 1 and 0 < u < W - 1:  # inside the image: a fixed 3 x 3, which the compiler unrolls
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                zn = depth[v + dv, u + du]
                jump = max(jump, abs(zn - z) if zn > 0 else np.float32(0.0))
        return jump
    v0, v1, u0, u1 = max(v - 1, 0), min(v + 1, H - 1), max(u - 1, 0), min(u + 1, W - 1)
    for vv in range(v0, v1 + 1):
        for uu in range(u0, u1 + 1):
            zn = depth[vv, uu]
            jump = max(jump, abs(zn - z) if zn > 0 else np.float32(0.0))
    return jump


@numba.njit(parallel=True, cache=True)
def _positional_uncertainty_kernel(depth, depth_std, has_std, rows, cols, sigma0, sigma2, z_ref, edge_weight, inv_voxel, out):
    for i in numba.prange(rows.shape[0]):
        v, u = rows[i], cols[i]
        z = depth[v, u]
        if has_std:
            sigma = depth_std[v, u]
        else:
            sigma = sigma0 + sigma2 * (z - z_ref) * (z - z_ref)
        out[i] = (sigma + edge_weight * edge_jump(depth, v, u)) * inv_voxel


def positional_uncertainty(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    rows: np.ndarray,  # [M] pixel rows of the observations
    cols: np.ndarray,  # [M] pixel columns
    voxel_size: float,
    depth_std: np.ndarray | None = None,  # [H, W] float32 metres
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
    edge_weight: float = 0.5,
) -> np.ndarray:  # [M] float32, in voxel units
    """U_pos at the given pixels (numba; `positional_uncertainty_reference` is the torch definition)."""
    out = np.empty(rows.shape[0], np.float32)
    std = depth_std if depth_std is not None else np.zeros((1, 1), np.float32)
    _positional_uncertainty_kernel(depth, std, depth_std is not None, rows.astype(np.int64, copy=False), cols.astype(np.int64, copy=False),
                                   np.float32(sigma0), np.float32(sigma2), np.float32(z_ref),
                                   np.float32(edge_weight), np.float32(1.0 / voxel_size), out)
    return out


def positional_uncertainty_reference(
    depth: Tensor,  # [H, W] float32, 0 = missing
    voxel_size: float,
    depth_std: Tensor | None = None,  # [H, W]
    sigma0: float = 0.0012,
    sigma2: float = 0.0019,
    z_ref: float = 0.4,
    edge_weight: float = 0.5,
) -> Tensor:  # [H, W] in voxel units (meaningful where depth > 0)
    """Whole-image PyTorch definition of U_pos."""
    H, W = depth.shape
    sigma = depth_std if depth_std is not None else sensor_depth_std(depth, sigma0, sigma2, z_ref)
    padded = torch.nn.functional.pad(depth[None, None], (1, 1, 1, 1))[0, 0]
    jump = torch.zeros_like(depth)
    for dv in range(3):
        for du in range(3):
            zn = padded[dv: dv + H, du: du + W]
            jump = torch.maximum(jump, torch.where(zn > 0, (zn - depth).abs(), torch.zeros_like(depth)))
    return (sigma + edge_weight * jump) / voxel_size


class AppearanceUncertainty(nn.Module):
    """U_app = ReLU(MLP(F_view)), per pixel with shared weights.

    The last layer starts at zero, so U_app = 0 at the analytic initialisation (reliability is then
    purely geometric) and training can learn which appearances to distrust.
    """

    def __init__(self, feature_dim: int, hidden: int = 16):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(feature_dim, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        nn.init.zeros_(self.mlp[2].weight)
        nn.init.zeros_(self.mlp[2].bias)

    @property
    def is_zero(self) -> bool:
        """True while the output layer is zero, i.e. U_app == 0 for every input (skip the MLP)."""
        last = self.mlp[2]
        return bool((last.weight == 0).all() and (last.bias <= 0).all())

    def forward(self, features: Tensor) -> Tensor:  # [M, L] -> [M]
        return torch.relu(self.mlp(features)).squeeze(-1)


def reliability(
    u_pos: Tensor,  # [M] voxel units
    u_app: Tensor,  # [M]
) -> Tensor:  # [M] in (0, 1]
    """R_view = exp(-U_pos) * exp(-U_app)."""
    return torch.exp(-u_pos) * torch.exp(-u_app)
