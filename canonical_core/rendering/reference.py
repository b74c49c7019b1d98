"""Reference compositor in plain PyTorch: exact, differentiable with autograd, slow.

Each 16x16 tile evaluates every splat whose support touches it at every pixel of the tile
(O(splats x pixels) per tile), so it suits tests and training on small images.
"""

from __future__ import annotations

from typing import Iterator

import torch
from torch import Tensor

from .projection import Blend, Splats
from .splat_geometry import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, SUPPORT_SIGMAS, TILE_SIZE


def tile_weights(
    splats: Splats,
    ids: Tensor,  # [m] splats touching the tile, front to back
    pixels: Tensor,  # [P, 2] pixel centres (u, v)
) -> tuple[Tensor, Tensor]:  # weights w = alpha T_before [P, m], transmittance after each splat [P, m]
    """Each splat's compositing weight at each pixel; zero where it is cut off or blending stopped."""
    means2d, conics = splats.means2d[ids], splats.conics[ids]
    dx = means2d[None, :, 0] - pixels[:, 0:1]
    dy = means2d[None, :, 1] - pixels[:, 1:2]
    a, b2, c = conics[None, :, 0], conics[None, :, 1] + conics[None, :, 1], conics[None, :, 2]
    # Written as in the numba kernel, so q rounds identically.
    q = a * dx * dx + b2 * dx * dy + c * dy * dy
    alpha = torch.clamp(splats.opacities[ids][None] * torch.exp(-0.5 * q), max=MAX_ALPHA)
    alpha = torch.where((q <= SUPPORT_SIGMAS**2) & (alpha >= MIN_ALPHA), alpha, torch.zeros_like(alpha))
    ones = alpha.new_ones(alpha.shape[0], 1)
    transmittance_after = torch.cumprod(1 - alpha, dim=1)
    transmittance_before = torch.cat([ones, transmittance_after[:, :-1]], 1)
    # Transmittance only falls, so "stop before the splat that takes it below the threshold"
    # is the prefix where the transmittance after each splat is still above it.
    kept = transmittance_after >= MIN_TRANSMITTANCE
    weights = torch.where(kept, alpha * transmittance_before, torch.zeros_like(alpha))
    return weights, torch.where(kept, transmittance_after, torch.ones_like(alpha))


def tiles(splats: Splats, width: int, height: int) -> Iterator[tuple[Tensor, Tensor]]:
    """Row-major over the image's tiles: (ids [m] of the splats touching the tile, front to back,
    pixel centres [256, 2] of the tile, overhanging the image in the last row/column of tiles)."""
    dtype, device = splats.means2d.dtype, splats.means2d.device
    offsets = torch.arange(TILE_SIZE, dtype=dtype, device=device)
    local_v, local_u = torch.meshgrid(offsets, offsets, indexing="ij")
    local = torch.stack([local_u.reshape(-1), local_v.reshape(-1)], -1)  # [256, 2] row-major
    x0, x1, y0, y1 = splats.tile_ranges.unbind(-1)
    for ty in range(-(-height // TILE_SIZE)):
        for tx in range(-(-width // TILE_SIZE)):
            ids = ((x0 <= tx) & (tx < x1) & (y0 <= ty) & (ty < y1)).nonzero().squeeze(1)
            yield ids, local + torch.tensor([tx * TILE_SIZE, ty * TILE_SIZE], dtype=dtype, device=device)


def _composite_tile(
    splats: Splats,
    ids: Tensor,  # [m] splats touching the tile, front to back
    pixels: Tensor,  # [P, 2] pixel centres (u, v)
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:  # per pixel: values [P, D], depth, weight sums,
    # transmittance, median depth
    weights, transmittance_after = tile_weights(splats, ids, pixels)
    before_and_after = torch.cat([weights.new_ones(weights.shape[0], 1), transmittance_after], 1)
    transmittance = before_and_after.amin(dim=1)
    # the splat at which the transmittance first falls below 1/2 (after the stop it reads 1: never)
    crosses_half = (before_and_after[:, :-1] >= 0.5) & (transmittance_after < 0.5)
    median_depth = torch.where(crosses_half, splats.depths[ids][None], torch.zeros_like(weights)).sum(1)
    return weights @ splats.values[ids], weights @ splats.depths[ids], weights.sum(1), transmittance, median_depth


def composite_reference(
    splats: Splats,
    width: int,
    height: int,
) -> Blend:
    """Front-to-back alpha compositing of depth-sorted ``splats``, tile by tile."""
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    parts_per_tile = [_composite_tile(splats, ids, pixels) for ids, pixels in tiles(splats, width, height)]

    def assemble(parts: list[Tensor]) -> Tensor:  # tiles of [256, ...] -> [H, W, ...]
        grid = torch.stack(parts).reshape(tiles_y, tiles_x, TILE_SIZE, TILE_SIZE, *parts[0].shape[1:])
        image = grid.transpose(1, 2).reshape(tiles_y * TILE_SIZE, tiles_x * TILE_SIZE, *parts[0].shape[1:])
        return image[:height, :width]  # the last row/column of tiles may overhang the image

    return Blend(*(assemble(list(parts)) for parts in zip(*parts_per_tile)))
