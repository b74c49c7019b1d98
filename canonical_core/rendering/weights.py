"""``blend_weights``: each Gaussian's compositing weight w_i(p) = alpha_i(p) T_i(p) at each pixel.

A render is linear in the per-Gaussian values given these weights (colour(p) = sum_i w_i(p) c_i),
so they are the matrix of any least-squares fit of Gaussian values to images
(`canonical_core.decode.solve_colours`). The reference takes them from the PyTorch compositor's
tiles; the fast path is a numba kernel over the cpu backend's projection and tile bins, with the
same image model (`splat_geometry`): both agree to float rounding.
"""

from __future__ import annotations

from typing import Literal, NamedTuple, get_args

import numba
import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from .cpu_tiles import bin_splats_by_tile, project_records, stable_depth_order
from .projection import project_splats
from .reference import tiles, tile_weights
from .splat_geometry import (
    CONIC_A, CONIC_B, CONIC_C, DEPTH, MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, OPACITY, SUPPORT, TILE_SIZE, U, V,
)  # fmt: skip

WeightsBackend = Literal["reference", "cpu"]


class BlendWeights(NamedTuple):
    """Sparse compositing weights of one view: entry k says Gaussian ``ids[k]`` adds
    ``weights[k]`` x its value to pixel ``pixels[k]`` (row-major index v * W + u)."""

    pixels: Tensor  # [K] int64
    ids: Tensor  # [K] int64
    weights: Tensor  # [K] float32


def _weights_reference(gaussians: Gaussians, camera: Camera, near_plane: float, min_weight: float) -> BlendWeights:
    with torch.no_grad():
        splats = project_splats(gaussians, camera, (), near_plane)
        parts = []
        for ids, pixels in tiles(splats, camera.width, camera.height):
            weights, _ = tile_weights(splats, ids, pixels)
            pixel, splat = ((weights >= min_weight) & (pixels[:, 0:1] < camera.width)
                            & (pixels[:, 1:2] < camera.height)).nonzero(as_tuple=True)  # fmt: skip
            index = pixels[pixel, 1].long() * camera.width + pixels[pixel, 0].long()
            parts.append((index, splats.ids[ids[splat]], weights[pixel, splat].float()))
    if not parts:
        empty = torch.zeros(0, dtype=torch.int64)
        return BlendWeights(empty, empty, torch.zeros(0))
    return BlendWeights(*(torch.cat(column) for column in zip(*parts)))


@numba.njit(parallel=True, cache=True)
def _tile_weights_numba(
    tile_starts: np.ndarray,  # [T + 1] int64
    splat_ids: np.ndarray,  # [K] int32 per tile, front to back
    splats: np.ndarray,  # [N, SPLAT_RECORD] float32
    boxes: np.ndarray,  # [N, 4] int32
    tiles_x: int,
    width: int,
    height: int,
    min_weight: float,
    starts: np.ndarray,  # [T] int64 where each tile's entries go
    out_pixels: np.ndarray,  # [E] int64 (written when fill)
    out_splats: np.ndarray,  # [E] int32
    out_weights: np.ndarray,  # [E] float32
    counts: np.ndarray,  # [T] int64 entries per tile (written when not fill)
    fill: bool,
) -> None:
    """Per tile, per pixel, the splats front to back as the C compositor blends them (float32
    alpha, float64 transmittance, stop before T < 1e-4); counts or writes the weights >= min_weight."""
    for tile in numba.prange(tile_starts.shape[0] - 1):
        u0, v0 = (tile % tiles_x) * TILE_SIZE, (tile // tiles_x) * TILE_SIZE
        k = starts[tile] if fill else 0
        for v in range(v0, min(v0 + TILE_SIZE, height)):
            for u in range(u0, min(u0 + TILE_SIZE, width)):
                transmittance = 1.0
                for j in range(tile_starts[tile], tile_starts[tile + 1]):
                    s = splat_ids[j]
                    if u < boxes[s, 0] or u > boxes[s, 1] or v < boxes[s, 2] or v > boxes[s, 3]:
                        continue
                    r = splats[s]
                    dx, dy = r[U] - np.float32(u), r[V] - np.float32(v)
                    q = r[CONIC_A] * dx * dx + (r[CONIC_B] + r[CONIC_B]) * dx * dy + r[CONIC_C] * dy * dy
                    if q > r[SUPPORT]:
                        continue
                    alpha = min(r[OPACITY] * np.float32(np.exp(np.float32(-0.5) * q)), np.float32(MAX_ALPHA))
                    if alpha < np.float32(MIN_ALPHA):
                        continue
                    after = transmittance * (1.0 - alpha)
                    if after < MIN_TRANSMITTANCE:
                        break
                    weight = alpha * np.float32(transmittance)
                    transmittance = after
                    if weight >= min_weight:
                        if fill:
                            out_pixels[k], out_splats[k], out_weights[k] = v * width + u, s, weight
                        k += 1
        if not fill:
            counts[tile] = k


def _weights_cpu(gaussians: Gaussians, camera: Camera, near_plane: float, min_weight: float) -> BlendWeights:
    width, height = camera.width, camera.height
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    records, boxes = project_records(gaussians, camera, near_plane)
    # Binning in global stable depth order leaves every tile's list front to back, the order the
    # compositor sorts each tile into; culled splats (empty boxes) are never binned.
    order = stable_depth_order(np.ascontiguousarray(np.where(boxes[:, 0] <= boxes[:, 1], records[:, DEPTH], np.float32(np.inf))))
    records, boxes = np.ascontiguousarray(records[order]), np.ascontiguousarray(boxes[order])
    tile_starts, splat_ids = bin_splats_by_tile(boxes, tiles_x, tiles_x * tiles_y, numba.get_num_threads())
    num_tiles = tiles_x * tiles_y
    counts = np.zeros(num_tiles, np.int64)
    no_pixels, no_splats, no_weights = np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.float32)
    args = (tile_starts, splat_ids, records, boxes, tiles_x, width, height, min_weight)
    _tile_weights_numba(*args, np.zeros(num_tiles, np.int64), no_pixels, no_splats, no_weights, counts, False)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    pixels, splats, weights = np.empty(starts[-1], np.int64), np.empty(starts[-1], np.int32), np.empty(starts[-1], np.float32)
    _tile_weights_numba(*args, starts[:-1], pixels, splats, weights, counts, True)
    ids = torch.from_numpy(order.astype(np.int64))[torch.from_numpy(splats).long()]
    return BlendWeights(torch.from_numpy(pixels), ids, torch.from_numpy(weights))


def blend_weights(
    gaussians: Gaussians,
    camera: Camera,
    backend: WeightsBackend = "cpu",
    near_plane: float = 0.01,
    min_weight: float = 1e-4,
) -> BlendWeights:
    """The compositing weights of ``gaussians`` at ``camera``, at least ``min_weight`` each.

    Summing ``weights[k] * values[ids[k]]`` into ``pixels[k]`` reproduces what `render` composites
    (up to the dropped weights below ``min_weight``), e.g. the colour before the background.

    Example (one Gaussian of opacity 0.8 straight ahead; its centre falls on pixel (8, 8)):
        >>> from canonical_core.camera import Camera
        >>> camera = Camera(K=[[40, 0, 8], [0, 40, 8], [0, 0, 1]], c2w=np.eye(4), width=16, height=16)
        >>> g = Gaussians(means=torch.tensor([[0.0, 0.0, 2.0]]), scales=torch.full((1, 3), 0.05),
        ...               quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacities=torch.tensor([0.8]), sh=torch.zeros(1, 1, 3))
        >>> w = blend_weights(g, camera)
        >>> round(float(w.weights[w.pixels == 8 * 16 + 8][0]), 3), len(w.weights) > 1
        (0.8, True)

    Raises:
        ValueError: an unknown backend, or a negative ``min_weight``.
    """
    if backend not in get_args(WeightsBackend):
        raise ValueError(f"backend: expected one of {list(get_args(WeightsBackend))}, got {backend!r}")
    if not min_weight >= 0:
        raise ValueError(f"min_weight: expected a non-negative weight, got {min_weight!r}")
    if backend == "reference":
        return _weights_reference(gaussians, camera, near_plane, min_weight)
    return _weights_cpu(gaussians, camera, near_plane, min_weight)
