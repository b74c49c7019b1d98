"""Training-free baselines without fusion: pixel-aligned Gaussians, and the same merged per voxel.

``pixel_aligned`` is the training-free analog of feed-forward pixel-aligned splatting (DepthSplat,
MVSplat): one Gaussian per valid pixel of every input view, nothing fused.
- mean: the pixel lifted with its depth;
- shape: a flat disc facing the camera (axes = the camera's x, y, z), in-plane std = the pixel
  footprint z / f times a coverage gain, thickness 0.1 x the in-plane std;
- colour: the pixel's colour (SH degree 0); features: the pixel's F_view (the same training-free
  extractor the scene fuses), so feature splats are comparable; labels: the frame's label scores at
  the pixel (when it carries them), as the scene samples them for fusion;
- opacity: the decoder's analytic opacity at full support, the value ``plain_decoding`` gives
  every Gaussian, so the two differ only in fusion.

Coverage gain. Valid depth pixels form a lattice with spacing d = (z / f) / sqrt(rho), rho the
local fraction of pixels with valid depth (5 x 5 window; sensor depth has holes, on the shelf
capture about 60 % valid inside surfaces and a grid of missing rows and columns). Equal Gaussians
on a lattice of spacing d sum to sum_k exp(-|x - k d|^2 / 2 s^2), whose relative ripple is
2 exp(-2 pi^2 s^2 / d^2) per axis (Poisson summation): 8.5 % at s = 0.4 d (the area-matching
std d / sqrt(2 pi)), 1.4 % at s = d / 2. We take s = d / 2, the smallest std at which the discs
close the surface into a flat field without see-through gaps, i.e. gain = 0.5 / sqrt(rho).

``gaussian_merge`` is the analog of merging pixel-aligned Gaussians after decoding (AnySplat-style
voxel merging): the pixel-aligned Gaussians of all views grouped by voxel, each group replaced by
one Gaussian with the members' mean position, colour, opacity and features, and the
moment-matched covariance mean_i(Sigma_i + (mu_i - mu)(mu_i - mu)^T).
"""

from __future__ import annotations

import dataclasses

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..calibration import quaternion_to_matrix
from ..decode import GaussianDecoder, matrix_to_quaternion
from ..evidence.extract import frame_features, lift_pixels
from ..evidence.features import sample_client_labels
from ..frame import Frame
from ..gaussians import Gaussians, rgb_to_sh_dc
from ..scene import SceneConfig

SPACING_FRACTION = 0.5  # in-plane std / local sample spacing (see the module docstring)
DENSITY_WINDOW = 5  # pixels: window of the local valid-depth fraction
THICKNESS = 0.1  # disc std along the viewing axis / in-plane std


def full_support_opacity(decoder: GaussianDecoder) -> float:
    """The decoder's opacity at full support, sigmoid(head(r = 1))."""
    with torch.no_grad():
        return float(torch.sigmoid(decoder.opacity(torch.ones(1)))[0])


def _cat(parts: Sequence[Gaussians]) -> Gaussians:
    def cat(name: str) -> Tensor | None:
        tensors = [getattr(p, name) for p in parts]
        return None if tensors[0] is None else torch.cat(tensors)

    return Gaussians(**{f.name: cat(f.name) for f in dataclasses.fields(Gaussians)})


def _covariances(scales: Tensor, rotations: Tensor) -> Tensor:  # [N, 3], [N, 3, 3] -> [N, 3, 3]
    return (rotations * scales[:, None, :] ** 2) @ rotations.transpose(1, 2)


def pixel_gaussians(frame: Frame, config: SceneConfig, opacity: float, features: bool = True) -> Gaussians:
    """One camera-facing disc per pixel whose depth lies in (config.range.near, config.range.far)."""
    if frame.depth is None:
        raise ValueError("depth: pixel-aligned Gaussians need depth")
    depth = frame.depth
    valid = (depth > config.range.near) & (depth < config.range.far)  # [H, W]
    density = F.avg_pool2d(valid[None, None].float(), DENSITY_WINDOW, stride=1, padding=DENSITY_WINDOW // 2,
                           count_include_pad=False)[0, 0]  # [H, W], > 0 wherever valid
    rows, cols = (t.numpy() for t in torch.nonzero(valid, as_tuple=True))
    points, colors = lift_pixels(frame, rows, cols)
    z = depth[rows, cols]
    gain = SPACING_FRACTION / density[rows, cols].sqrt()
    cam = frame.camera
    sx, sy = gain * z / cam.fx, gain * z / cam.fy
    scales = torch.stack([sx, sy, THICKNESS * torch.minimum(sx, sy)], -1)
    rotation = torch.from_numpy(cam.c2w64()[:3, :3].astype(np.float32))
    m = len(rows)
    return Gaussians(
        means=torch.from_numpy(points),
        scales=scales,
        quats=matrix_to_quaternion(rotation[None]).expand(m, 4).contiguous(),
        opacities=torch.full((m,), opacity),
        sh=rgb_to_sh_dc(torch.from_numpy(colors))[:, None, :],
        features=torch.from_numpy(frame_features(frame, rows, cols, config)) if features else None,
        labels=None if frame.labels is None else torch.from_numpy(sample_client_labels(frame, rows, cols)),
    )


def pixel_aligned(frames: Sequence[Frame], voxel_size: float, features: bool = True) -> Gaussians:
    """Pixel-aligned Gaussians of every frame, concatenated (no fusion)."""
    if not frames:
        raise ValueError("frames: expected at least one frame")
    config = SceneConfig(voxel_size=voxel_size)
    opacity = full_support_opacity(GaussianDecoder(config.features.dim))
    return _cat([pixel_gaussians(f, config, opacity, features) for f in frames])


def merge_per_voxel(gaussians: Gaussians, voxel_size: float) -> Gaussians:
    """One moment-matched Gaussian per occupied voxel of side ``voxel_size`` (module docstring)."""
    if not voxel_size > 0:
        raise ValueError(f"voxel_size: expected a positive number, got {voxel_size!r}")
    cells = torch.floor(gaussians.means / voxel_size).to(torch.int64)
    _, group = torch.unique(cells, dim=0, return_inverse=True)  # [N] voxel of each Gaussian
    k = int(group.max()) + 1 if len(group) else 0
    count = torch.zeros(k).index_add_(0, group, torch.ones(len(group)))[:, None]  # [K, 1]

    def mean(values: Tensor) -> Tensor:  # [N, ...] -> [K, ...] float64 group means
        v = values.double().reshape(len(values), -1)
        out = torch.zeros(k, v.shape[1], dtype=torch.float64).index_add_(0, group, v) / count.double()
        return out.reshape(k, *values.shape[1:])

    mu = mean(gaussians.means)  # [K, 3]
    d = gaussians.means.double() - mu[group]
    cov = mean(_covariances(gaussians.scales.double(), torch.from_numpy(quaternion_to_matrix(gaussians.quats.double().numpy())))
               + d[:, :, None] * d[:, None, :])  # [K, 3, 3]
    eigval, eigvec = torch.linalg.eigh(0.5 * (cov + cov.transpose(1, 2)))
    eigvec = torch.where((torch.linalg.det(eigvec) < 0)[:, None, None], eigvec * eigvec.new_tensor([1.0, 1.0, -1.0]), eigvec)
    return Gaussians(
        means=mu.float(),
        scales=eigval.clamp_min(0.0).sqrt().float(),
        quats=matrix_to_quaternion(eigvec.float()),
        opacities=mean(gaussians.opacities).float(),
        sh=mean(gaussians.sh).float(),
        features=None if gaussians.features is None else mean(gaussians.features).float(),
        labels=None if gaussians.labels is None else mean(gaussians.labels).float(),
    )


def gaussian_merge(frames: Sequence[Frame], voxel_size: float, features: bool = True) -> Gaussians:
    """Pixel-aligned Gaussians of all frames merged per voxel."""
    return merge_per_voxel(pixel_aligned(frames, voxel_size, features), voxel_size)
