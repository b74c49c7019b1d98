"""Projection of Gaussians to depth-sorted screen-space splats in PyTorch (differentiable).

The reference backend composites these; the image model and the shared arithmetic are in
`splat_geometry`. Also the per-Gaussian channel values (SH colour, features, label scores) that
every backend composites.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from .sh import sh_to_rgb
from .splat_geometry import (
    BOX_PADDING, LOW_PASS, MIN_ALPHA, MIN_QUAT_NORM2, SUPPORT_SIGMAS, TILE_SIZE, camera_point, screen_geometry, slope_bounds,
)  # fmt: skip

Channel = Literal["rgb", "features", "labels"]


@dataclass
class Splats:
    """Visible Gaussians projected to the screen, sorted front to back (stable in input order).

    Everything but ``tile_ranges`` carries autograd history back to the Gaussians.
    """

    means2d: Tensor  # [M, 2] pixel coordinates (u, v) of the centres
    conics: Tensor  # [M, 3] (a, b, c) of Sigma_2D^-1, q = a dx^2 + 2 b dx dy + c dy^2
    depths: Tensor  # [M] view-space z
    opacities: Tensor  # [M]
    values: Tensor  # [M, D] channels to composite: rgb, features, label scores as requested
    tile_ranges: Tensor  # [M, 4] int32 (x0, x1, y0, y1): half-open range of tiles the support touches
    ids: Tensor  # [M] int64 index of each splat's Gaussian


class Blend(NamedTuple):
    """Per-pixel sums of front-to-back compositing, before normalisation and background."""

    values: Tensor  # [H, W, D] sum of w_i v_i
    depth_sums: Tensor  # [H, W] sum of w_i z_i
    weight_sums: Tensor  # [H, W] sum of w_i: 1 - transmittance in exact arithmetic, precise where alpha is small
    transmittance: Tensor  # [H, W] product of (1 - alpha_i) over the blended splats
    median_depth: Tensor | None = None  # [H, W] z of the splat at which the transmittance first falls
    # below 1/2, 0 where it never does; None from a backend that cannot tell (gsplat)


def world_to_camera(camera: Camera, dtype: torch.dtype, device: torch.device) -> Tensor:  # [4, 4]
    """The view matrix, inverted in float64 before the cast so float64 renders stay exact."""
    return torch.from_numpy(np.linalg.inv(camera.c2w64())).to(dtype=dtype, device=device)


def channel_values(
    gaussians: Gaussians,
    camera: Camera,
    channels: Sequence[Channel],
    colour: Callable[[Tensor, Tensor], Tensor] = sh_to_rgb,  # (sh [N, K, 3], dirs [N, 3]) -> rgb [N, 3]
) -> Tensor:  # [N, D]
    """The per-Gaussian values to composite, concatenated in the order of ``channels``; ``colour``
    evaluates the SH (`sh_to_rgb`, or its fast path for the cpu backend). "labels" is S + 1 columns:
    the scores, then whether the Gaussian has any label evidence (its scores not all 0), whose blend
    says how much of a pixel's weight has labels."""
    dtype = gaussians.means.dtype
    parts = []
    for channel in channels:
        if channel == "rgb":
            center = torch.from_numpy(camera.c2w64()[:3, 3]).to(dtype=dtype, device=gaussians.means.device)
            parts.append(colour(gaussians.sh.to(dtype), gaussians.means - center).to(gaussians.means))
        elif channel == "labels":  # the scores, and 1 for a Gaussian with label evidence
            scores = gaussians.labels.to(dtype)
            parts += [scores, scores.ne(0).any(-1, keepdim=True).to(dtype)]
        else:
            parts.append(getattr(gaussians, channel).to(dtype))
    if not parts:
        return gaussians.means.new_zeros(len(gaussians), 0)
    return torch.cat(parts, -1)


def pixel_boxes(
    means2d: Tensor,  # [N, 2]
    variances: Tensor,  # [N, 2] diagonal of Sigma_2D
    opacities: Tensor,  # [N]
    width: int,
    height: int,
) -> Tensor:  # [N, 4] float (u_lo, u_hi, v_lo, v_hi), clipped to the image; empty where lo > hi
    """Pixel centres that can receive a splat: q <= min(9, 2 ln(255 opacity)), padded. The same
    rule as `project_numba`'s boxes, so both backends bin a splat into the same tiles."""
    support_q = torch.clamp(2 * torch.log(opacities * 255.0), min=0.0, max=SUPPORT_SIGMAS**2)
    half = torch.sqrt(support_q[:, None] * variances) + BOX_PADDING
    lo = torch.ceil(means2d - half).clamp_min(0.0)
    hi = torch.minimum(torch.floor(means2d + half), means2d.new_tensor([width - 1.0, height - 1.0]))
    return torch.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], -1)


def project_splats(
    gaussians: Gaussians,
    camera: Camera,
    channels: Sequence[Channel],
    near_plane: float,
) -> Splats:
    """Project, cull and depth-sort ``gaussians`` for ``camera`` (differentiable, any device)."""
    dtype, device = gaussians.means.dtype, gaussians.means.device
    view = world_to_camera(camera, dtype, device)[:3].reshape(-1).tolist()
    means = gaussians.means
    x, y, z = camera_point(means[:, 0], means[:, 1], means[:, 2], view)
    opacities = gaussians.opacities.to(dtype)
    with torch.no_grad():
        candidates = ((z >= near_plane) & (opacities >= MIN_ALPHA)).nonzero().squeeze(1)
    x, y, z = x[candidates], y[candidates], z[candidates]
    quats = gaussians.quats[candidates].to(dtype)
    scales = gaussians.scales[candidates].to(dtype)
    qw, qx, qy, qz = quats.unbind(-1)
    quat_norm2 = (qw * qw + qx * qx + qy * qy + qz * qz).clamp_min(MIN_QUAT_NORM2)
    u_min, u_max, v_min, v_max = slope_bounds(camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)
    u, v, a, b, c, var_u, var_v = screen_geometry(
        x, y, z, (x / z).clamp(u_min, u_max), (y / z).clamp(v_min, v_max), qw, qx, qy, qz, quat_norm2,
        scales[:, 0], scales[:, 1], scales[:, 2], view, camera.fx, camera.fy, camera.cx, camera.cy, LOW_PASS,
    )  # fmt: skip
    means2d, conics = torch.stack([u, v], -1), torch.stack([a, b, c], -1)
    with torch.no_grad():
        variances = torch.stack([var_u, var_v], -1)
        finite = torch.isfinite(torch.cat([means2d, conics, variances], -1)).all(-1)
        boxes = pixel_boxes(means2d, variances, opacities[candidates], camera.width, camera.height)
        on_screen = (boxes[:, 0] <= boxes[:, 1]) & (boxes[:, 2] <= boxes[:, 3])
        visible = (finite & on_screen).nonzero().squeeze(1)
        visible = visible[torch.argsort(z[visible], stable=True)]
        tile_ranges = torch.div(boxes[visible].to(torch.int32), TILE_SIZE, rounding_mode="floor")
        tile_ranges[:, [1, 3]] += 1
    order = candidates[visible]
    return Splats(
        means2d=means2d[visible],
        conics=conics[visible],
        depths=z[visible],
        opacities=opacities[order],
        values=channel_values(gaussians.index(order), camera, channels),
        tile_ranges=tile_ranges,
        ids=order,
    )
