"""Scene builders for the rendering tests: small random scenes and hand-placed Gaussians."""

from __future__ import annotations

import math

import numpy as np
import torch

from canonical_core.camera import Camera
from canonical_core.gaussians import Gaussians, rgb_to_sh_dc


def look_at_camera(width: int, height: int, focal: float, eye, target, roll: float = 0.0) -> Camera:
    """A camera at ``eye`` looking at ``target`` (OpenCV axes), rolled about its optical axis."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    roll_rotation = np.array([[math.cos(roll), -math.sin(roll), 0], [math.sin(roll), math.cos(roll), 0], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], 1) @ roll_rotation
    c2w[:3, 3] = eye
    K = [[focal, 0, (width - 1) / 2 + 0.3], [0, focal, (height - 1) / 2 - 0.2], [0, 0, 1]]
    return Camera(K=K, c2w=c2w, width=width, height=height)


def random_scene(
    n: int,
    seed: int,
    sh_degree: int = 1,
    feature_dim: int | None = 5,
    label_dim: int | None = 4,
    scale_range: tuple[float, float] = (0.02, 0.15),
    opacity_range: tuple[float, float] = (0.05, 1.0),
    spread: float = 1.0,
    dtype: torch.dtype = torch.float32,
) -> Gaussians:
    """n Gaussians in a ball of radius ``spread`` around the origin, anisotropic, random colours."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=g, dtype=dtype)  # noqa: E731
    low, high = scale_range
    sh = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=dtype) * 0.3
    sh[:, 0] = rgb_to_sh_dc(rand(n, 3) * 0.8 + 0.1)
    return Gaussians(
        means=(rand(n, 3) * 2 - 1) * spread,
        scales=low + (high - low) * rand(n, 3),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        opacities=opacity_range[0] + (opacity_range[1] - opacity_range[0]) * rand(n),
        sh=sh,
        features=None if feature_dim is None else torch.randn(n, feature_dim, generator=g, dtype=dtype),
        labels=None if label_dim is None else rand(n, label_dim),
    )


def gaussians_at(means, scales, opacities, colors, dtype: torch.dtype = torch.float32) -> Gaussians:
    """Axis-aligned Gaussians with the given means [N, 3], scales [N, 3], opacities [N], colours [N, 3]."""
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    return Gaussians(
        means=means,
        scales=torch.as_tensor(scales, dtype=dtype).reshape(n, 3),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype).repeat(n, 1),
        opacities=torch.as_tensor(opacities, dtype=dtype).reshape(n),
        sh=rgb_to_sh_dc(torch.as_tensor(colors, dtype=dtype).reshape(n, 1, 3)),
    )


def pinhole(width: int, height: int, focal: float, cx: float, cy: float) -> Camera:
    """A camera at the origin looking down +z."""
    return Camera(K=[[focal, 0, cx], [0, focal, cy], [0, 0, 1]], c2w=np.eye(4), width=width, height=height)
