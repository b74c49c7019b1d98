"""Reference compositor in plain PyTorch: exact, differentiable with autograd, slow.

Each 16x16 tile evaluates every splat whose support touches it at every pixel of the tile
(O(splats x pixels) per tile), so it suits tests and training on small images.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .projection import Blend, Splats
from .splat_geometry import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE, SUPPORT_SIGMAS, TILE_SIZE


def _composite_tile(
    splats: Splats,
    ids: Tensor,  # [m] splats touching the tile, front to back
    pixels: Tensor,  # [P, 2] pixel centres (u, v)
) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # per pixel: values [P, D], depth, weight sums, transmittance
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
    transmittance = torch.cat([ones, torch.where(kept, transmittance_after, ones)], 1).amin(dim=1)
    return weights @ splats.values[ids], weights @ splats.depths[ids], weights.sum(1), transmittance


def composite_reference(
    splats: Splats,
    width: int,
    height: int,
) -> Blend:
    """Front-to-back alpha compositing of depth-sorted ``splats``, tile by tile."""
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    dtype, device = splats.means2d.dtype, splats.means2d.device
    offsets = torch.arange(TILE_SIZE, dtype=dtype, device=device)
    local_v, local_u = torch.meshgrid(offsets, offsets, indexing="ij")
    local = torch.stack([local_u.reshape(-1), local_v.reshape(-1)], -1)  # [256, 2] row-major
    x0, x1, y0, y1 = splats.tile_ranges.unbind(-1)
    tiles = []
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            ids = ((x0 <= tx) & (tx < x1) & (y0 <= ty) & (ty < y1)).nonzero().squeeze(1)
            origin = torch.tensor([tx * TILE_SIZE, ty * TILE_SIZE], dtype=dtype, device=device)
            tiles.append(_composite_tile(splats, ids, local + origin))

    def assemble(parts: list[Tensor]) -> Tensor:  # tiles of [256, ...] -> [H, W, ...]
        grid = torch.stack(parts).reshape(tiles_y, tiles_x, TILE_SIZE, TILE_SIZE, *parts[0].shape[1:])
        image = grid.transpose(1, 2).reshape(tiles_y * TILE_SIZE, tiles_x * TILE_SIZE, *parts[0].shape[1:])
        return image[:height, :width]  # the last row/column of tiles may overhang the image

    return Blend(*(assemble(list(parts)) for parts in zip(*tiles)))
