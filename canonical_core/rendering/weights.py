"""``blend_weights``: each Gaussian's compositing weight w_i(p) = alpha_i(p) T_i(p) at each pixel;
``blend_weight_rows``: the same as one sparse row per pixel; ``weight_rows_and_blend``: the rows and
the view's RGB render (every weight in) from one pass.

A render is linear in the per-Gaussian values given these weights (colour(p) = sum_i w_i(p) c_i),
so they are the matrix of any least-squares fit of Gaussian values to images
(`canonical_core.decode.solve_colours`). The reference takes them from the PyTorch compositor's
tiles; the fast path is the C compositor's weights mode over the cpu backend's projection and tile
bins (the render's own arithmetic): both agree to float rounding.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, get_args

import numba
import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from ..gaussians.container import GEOMETRY, check_finite
from .cpu_tiles import bin_splats_by_tile, composite_weights, project_records
from .projection import Blend, project_splats
from .reference import composite_reference, tiles, tile_weights
from .sh import sh_to_rgb_fast
from .splat_geometry import TILE_SIZE

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
            pixel, splat = ((weights >= min_weight) & (weights > 0) & (pixels[:, 0:1] < camera.width)
                            & (pixels[:, 1:2] < camera.height)).nonzero(as_tuple=True)  # fmt: skip
            index = pixels[pixel, 1].long() * camera.width + pixels[pixel, 0].long()
            parts.append((index, splats.ids[ids[splat]], weights[pixel, splat].float()))
    if not parts:
        empty = torch.zeros(0, dtype=torch.int64)
        return BlendWeights(empty, empty, torch.zeros(0))
    return BlendWeights(*(torch.cat(column) for column in zip(*parts)))


@numba.njit(parallel=True, cache=True)
def _tile_bounds(
    tile_starts: np.ndarray,  # [T + 1] int64
    splat_ids: np.ndarray,  # [K] int32 per tile
    boxes: np.ndarray,  # [N, 4] int32 inclusive pixel boxes u0, u1, v0, v1
    tiles_x: int,
) -> np.ndarray:  # [T] int64 pixels of the tile inside each of its splats' boxes, summed
    """An upper bound on each tile's entries: one per (splat, box pixel in the tile)."""
    bounds = np.zeros(tile_starts.shape[0] - 1, np.int64)
    for tile in numba.prange(tile_starts.shape[0] - 1):
        u0, v0 = (tile % tiles_x) * TILE_SIZE, (tile // tiles_x) * TILE_SIZE
        total = 0
        for j in range(tile_starts[tile], tile_starts[tile + 1]):
            s = splat_ids[j]
            du = min(u0 + TILE_SIZE - 1, boxes[s, 1]) - max(u0, boxes[s, 0]) + 1
            dv = min(v0 + TILE_SIZE - 1, boxes[s, 3]) - max(v0, boxes[s, 2]) + 1
            total += max(du, 0) * max(dv, 0)
        bounds[tile] = total
    return bounds


@numba.njit(parallel=True, cache=True)
def _compact(
    starts: np.ndarray,  # [T] int64 where each tile's entries start in the bounded arrays
    counts: np.ndarray,  # [T] int64 entries per tile
    pixels: np.ndarray,  # [B] int32
    ids: np.ndarray,  # [B] int32
    weights: np.ndarray,  # [B] float32
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # the written entries, tile after tile: [E] each
    ends = np.cumsum(counts)
    out_pixels, out_ids, out_weights = np.empty(ends[-1], np.int64), np.empty(ends[-1], np.int64), np.empty(ends[-1], np.float32)
    for tile in numba.prange(starts.shape[0]):
        first = ends[tile] - counts[tile]
        for k in range(counts[tile]):
            out_pixels[first + k], out_ids[first + k] = pixels[starts[tile] + k], ids[starts[tile] + k]
            out_weights[first + k] = weights[starts[tile] + k]
    return out_pixels, out_ids, out_weights


@numba.njit(parallel=True, cache=True)
def _row_sums(
    starts: np.ndarray,  # [T] int64 where each tile's entries start in the bounded arrays
    counts: np.ndarray,  # [T] int64 entries per tile
    pixels: np.ndarray,  # [B] int32
    weights: np.ndarray,  # [B] float32
    row_counts: np.ndarray,  # [P] int32, zeros: each pixel's entries, added to
    alpha: np.ndarray,  # [P] float64, zeros: each pixel's summed weight, added to
) -> None:
    """Each pixel's entry count and weight sum (float64, front to back). A tile's entries touch only
    its own pixels, so tiles run in parallel without a race."""
    for tile in numba.prange(starts.shape[0]):
        for k in range(starts[tile], starts[tile] + counts[tile]):
            row_counts[pixels[k]] += 1
            alpha[pixels[k]] += weights[k]


@numba.njit(parallel=True, cache=True)
def _fill_rows(
    starts: np.ndarray,  # [T] int64
    counts: np.ndarray,  # [T] int64
    pixels: np.ndarray,  # [B] int32
    ids: np.ndarray,  # [B] int32
    weights: np.ndarray,  # [B] float32
    scale: np.ndarray,  # [P] float64 each row's factor, 0 for a row without entries
    cursor: np.ndarray,  # [P] int64 where each row's next entry goes (its start), advanced
    out_ids: np.ndarray,  # [E] int32
    out_weights: np.ndarray,  # [E] float32
) -> None:
    """Each tile's entries into their pixels' rows, in tile order (front to back within a row)."""
    for tile in numba.prange(starts.shape[0]):
        for k in range(starts[tile], starts[tile] + counts[tile]):
            p = pixels[k]
            if scale[p] > 0.0:
                at = cursor[p]
                out_ids[at], out_weights[at] = ids[k], weights[k] * scale[p]
                cursor[p] = at + 1


def _tile_entries(gaussians: Gaussians, camera: Camera, near_plane: float, min_weight: float, rgb: bool = False):
    """The fast path's weights in per-tile slots: (slot starts [T], counts [T], pixels, ids, weights),
    or None when no splat reaches the image; with ``rgb``, also the view's RGB blend from the same
    pass (a `Blend` without depth sums, as `render_cpu` would composite it; None with no entries)."""
    width, height = camera.width, camera.height
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    records, boxes, spare = project_records(gaussians, camera, near_plane)  # one per Gaussian, in input order
    tile_starts, splat_ids = bin_splats_by_tile(boxes, tiles_x, tiles_x * tiles_y, numba.get_num_threads())
    if len(splat_ids) == 0:
        return None
    # One pass of the compositor into per-tile slots as large as the tile's box pixels (32-bit: half the
    # memory traffic of 64-bit pixels and ids); it sorts each tile front to back as a render does
    bounds = _tile_bounds(tile_starts, splat_ids, boxes, tiles_x)
    starts = np.concatenate([[0], np.cumsum(bounds)[:-1]]).astype(np.int64)
    size = int(bounds.sum())
    pixels, ids, weights = np.empty(size, np.int32), np.empty(size, np.int32), np.empty(size, np.float32)
    counts = np.zeros(len(bounds), np.int64)
    sums = None
    if rgb:  # the colours into the splats' lines, as a render puts them
        values = spare[:, :3]
        sh_to_rgb_fast(gaussians.sh.detach().float(), gaussians.means.detach().float(),
                       camera.c2w64()[:3, 3].astype(np.float32), out=values)
        sums = (values, np.zeros((height, width, 3), np.float32), np.zeros((height, width), np.float32),
                np.ones((height, width), np.float32))
    composite_weights(tile_starts, splat_ids, records, boxes, tiles_x, width, height, min_weight, starts, pixels,
                      ids, weights, counts, numba.get_num_threads(), sums)
    entries = starts, counts, pixels, ids, weights
    if not rgb:
        return entries
    _, out_values, out_weight_sums, out_transmittance = sums
    return entries, Blend(torch.from_numpy(out_values), None, torch.from_numpy(out_weight_sums),
                          torch.from_numpy(out_transmittance))


def _weights_cpu(gaussians: Gaussians, camera: Camera, near_plane: float, min_weight: float) -> BlendWeights:
    entries = _tile_entries(gaussians, camera, near_plane, min_weight)
    if entries is None:
        empty = torch.zeros(0, dtype=torch.int64)
        return BlendWeights(empty, empty, torch.zeros(0))
    return BlendWeights(*(torch.from_numpy(a) for a in _compact(*entries)))


def _check(gaussians: Gaussians, backend: str, min_weight: float, near_plane: float) -> None:
    if backend not in get_args(WeightsBackend):
        raise ValueError(f"backend: expected one of {list(get_args(WeightsBackend))}, got {backend!r}")
    if not min_weight >= 0:
        raise ValueError(f"min_weight: expected a non-negative weight, got {min_weight!r}")
    if not 0 < near_plane < math.inf:  # as `render` refuses it: a Gaussian behind the camera would be weighed
        raise ValueError(f"near_plane: expected a positive, finite distance, got {near_plane!r}")
    check_finite(gaussians, GEOMETRY)


def blend_weights(
    gaussians: Gaussians,
    camera: Camera,
    backend: WeightsBackend = "cpu",
    near_plane: float = 0.01,
    min_weight: float = 1e-4,
) -> BlendWeights:
    """The compositing weights of ``gaussians`` at ``camera``, at least ``min_weight`` each (a
    weight of zero is no entry, whatever ``min_weight``).

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
        ValueError: an unknown backend, a negative ``min_weight``, a near plane that is not a positive
            distance, or Gaussians with NaN or inf where they are.
    """
    _check(gaussians, backend, min_weight, near_plane)
    if backend == "reference":
        return _weights_reference(gaussians, camera, near_plane, min_weight)
    return _weights_cpu(gaussians, camera, near_plane, min_weight)


class WeightRows(NamedTuple):
    """The compositing weights of one view as compressed sparse rows, one row per pixel (row-major
    v * W + u), a row's entries front to back: pixel p takes ``weights[k]`` x the value of Gaussian
    ``ids[k]`` for k in ``starts[p]:starts[p + 1]``. When normalised, each row was divided by its
    alpha (the sum of its weights) and ``scale`` holds 1 / alpha, 0 for a row left empty."""

    starts: np.ndarray  # [P + 1] int32
    ids: np.ndarray  # [E] int32
    weights: np.ndarray  # [E] float32
    scale: np.ndarray  # [P] float64: the factor each row's weights were multiplied by


def _scales(alpha: np.ndarray, normalised_from: float | None) -> np.ndarray:  # [P] float64 -> [P] float64
    if normalised_from is None:
        return np.ones(len(alpha))
    covered = alpha >= normalised_from
    return np.divide(1.0, alpha, out=np.zeros(len(alpha)), where=covered)


def _rows_reference(w: BlendWeights, num_pixels: int, normalised_from: float | None) -> WeightRows:
    """`WeightRows` of entries in any order, by a stable sort on the pixel (PyTorch)."""
    order = torch.sort(w.pixels, stable=True).indices
    pixels, ids, weights = w.pixels[order], w.ids[order], w.weights[order]
    alpha = torch.zeros(num_pixels, dtype=torch.float64).index_add_(0, pixels, weights.double())
    scale = torch.from_numpy(_scales(alpha.numpy(), normalised_from))
    kept = scale[pixels] > 0
    counts = torch.bincount(pixels[kept], minlength=num_pixels)
    starts = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(counts, 0)])
    return WeightRows(starts.int().numpy(), ids[kept].int().numpy(),
                      (weights[kept].double() * scale[pixels[kept]]).float().numpy(), scale.numpy())


def _check_rows(gaussians: Gaussians, normalised_from: float | None, backend: str, min_weight: float,
                near_plane: float) -> None:
    if normalised_from is not None and (isinstance(normalised_from, bool) or not isinstance(normalised_from, (int, float))
                                        or not normalised_from > 0):
        raise ValueError(f"normalised_from: expected a positive alpha or None, got {normalised_from!r}")
    _check(gaussians, backend, min_weight, near_plane)


def _rows(entries, num_pixels: int, normalised_from: float | None) -> WeightRows:
    """`WeightRows` of the fast path's per-tile entries (`_tile_entries`; None: no entries)."""
    if entries is None:
        return WeightRows(np.zeros(num_pixels + 1, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32),
                          _scales(np.zeros(num_pixels), normalised_from))
    starts, counts, pixels, ids, weights = entries
    row_counts, alpha = np.zeros(num_pixels, np.int32), np.zeros(num_pixels)
    _row_sums(starts, counts, pixels, weights, row_counts, alpha)
    scale = _scales(alpha, normalised_from)
    row_counts[scale == 0] = 0
    row_starts = np.zeros(num_pixels + 1, np.int64)
    np.cumsum(row_counts, out=row_starts[1:])
    out_ids, out_weights = np.empty(row_starts[-1], np.int32), np.empty(row_starts[-1], np.float32)
    _fill_rows(starts, counts, pixels, ids, weights, scale, row_starts[:-1].copy(), out_ids, out_weights)
    return WeightRows(row_starts.astype(np.int32), out_ids, out_weights, scale)


def blend_weight_rows(
    gaussians: Gaussians,
    camera: Camera,
    normalised_from: float | None = None,
    backend: WeightsBackend = "cpu",
    near_plane: float = 0.01,
    min_weight: float = 1e-4,
) -> WeightRows:
    """`blend_weights` as one row per pixel (`WeightRows`), the matrix of a least-squares fit of
    Gaussian values to an image. With ``normalised_from``, each row is divided by its alpha, as a
    ``"normalised"`` render shows the pixel, and rows whose alpha is below it are left empty.

    The fast path writes the rows straight from the compositing kernel's per-tile slots (two
    passes over them, tiles in parallel); the reference sorts the reference `blend_weights` by pixel.

    Example (one Gaussian of opacity 0.8 straight ahead, its centre on pixel (8, 8)):
        >>> from canonical_core.camera import Camera
        >>> camera = Camera(K=[[40, 0, 8], [0, 40, 8], [0, 0, 1]], c2w=np.eye(4), width=16, height=16)
        >>> g = Gaussians(means=torch.tensor([[0.0, 0.0, 2.0]]), scales=torch.full((1, 3), 0.05),
        ...               quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), opacities=torch.tensor([0.8]), sh=torch.zeros(1, 1, 3))
        >>> rows = blend_weight_rows(g, camera, normalised_from=0.5)
        >>> centre = 8 * 16 + 8
        >>> rows.ids[rows.starts[centre]:rows.starts[centre + 1]].tolist(), round(float(rows.scale[centre]), 3)
        ([0], 1.25)

    Raises:
        ValueError: as `blend_weights`, or a ``normalised_from`` that is not a positive number.
    """
    _check_rows(gaussians, normalised_from, backend, min_weight, near_plane)
    num_pixels = camera.height * camera.width
    if backend == "reference":
        return _rows_reference(_weights_reference(gaussians, camera, near_plane, min_weight), num_pixels, normalised_from)
    return _rows(_tile_entries(gaussians, camera, near_plane, min_weight), num_pixels, normalised_from)


def weight_rows_and_blend(
    gaussians: Gaussians,
    camera: Camera,
    normalised_from: float | None = None,
    backend: WeightsBackend = "cpu",
    near_plane: float = 0.01,
    min_weight: float = 1e-4,
) -> tuple[WeightRows, Blend]:
    """`blend_weight_rows`, and the view's RGB blend with every weight in (a `Blend` without depth
    sums: what `render` composites, and `blend_rgb` turns into its image), from one pass of the
    compositor on the fast path. A fit over rows that leave small weights out still measures its
    residual against the whole render so.

    Raises:
        ValueError: as `blend_weight_rows`.
    """
    _check_rows(gaussians, normalised_from, backend, min_weight, near_plane)
    num_pixels, shape = camera.height * camera.width, (camera.height, camera.width)
    if backend == "reference":
        rows = _rows_reference(_weights_reference(gaussians, camera, near_plane, min_weight), num_pixels, normalised_from)
        with torch.no_grad():
            blend = composite_reference(project_splats(gaussians, camera, ("rgb",), near_plane), camera.width, camera.height)
        return rows, blend._replace(depth_sums=None)
    found = _tile_entries(gaussians, camera, near_plane, min_weight, rgb=True)
    if found is None:
        return _rows(None, num_pixels, normalised_from), Blend(torch.zeros(*shape, 3), None, torch.zeros(shape), torch.ones(shape))
    entries, blend = found
    return _rows(entries, num_pixels, normalised_from), blend
