"""CUDA compositor: gsplat's fused rasterizer, fed the same per-Gaussian channel values."""

from __future__ import annotations

from typing import Sequence

import torch

from ..camera import Camera
from ..gaussians import Gaussians
from .projection import Blend, Channel, channel_values, world_to_camera
from .splat_geometry import LOW_PASS, TILE_SIZE


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def composite_gsplat(
    gaussians: Gaussians,  # on a CUDA device
    camera: Camera,
    channels: Sequence[Channel],
    near_plane: float,
) -> Blend:
    """Render with ``gsplat.rasterization`` (differentiable). gsplat bounds each splat by its own
    screen-space radius, not the 3-sigma ellipse, so images differ slightly at splat edges."""
    import gsplat

    dtype, device = gaussians.means.dtype, gaussians.means.device
    w2c = world_to_camera(camera, dtype, device)
    values = channel_values(gaussians, camera, channels)
    # gsplat samples pixel (u, v) at (u + 0.5, v + 0.5); this project centres it at (u, v). Moving
    # the principal point half a pixel makes both sample the same rays.
    K = camera.K64().copy()
    K[:2, 2] += 0.5
    # Colours are evaluated here (not by gsplat's sh_degree path) so that RGB, features and
    # label scores go through one call; the expected depth comes back as the last channel.
    rendered, alpha, _ = gsplat.rasterization(
        means=gaussians.means,
        quats=gaussians.quats,
        scales=gaussians.scales,
        opacities=gaussians.opacities,
        colors=values,
        viewmats=w2c[None],
        Ks=torch.from_numpy(K).to(dtype=dtype, device=device)[None],
        width=camera.width,
        height=camera.height,
        near_plane=near_plane,
        eps2d=LOW_PASS,
        tile_size=TILE_SIZE,
        render_mode="RGB+ED" if values.shape[1] else "ED",
        rasterize_mode="classic",
    )
    rendered, alpha = rendered[0], alpha[0, ..., 0]
    return Blend(
        values=rendered[..., :-1], depth_sums=rendered[..., -1] * alpha, weight_sums=alpha, transmittance=1 - alpha
    )
