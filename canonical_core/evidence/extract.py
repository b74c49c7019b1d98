"""Ext: a frame -> its view-centric evidence (lifted points, colours, features, reliability)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch

from ..frame import Frame
from ..rendering.sh import sh_basis_at_points  # the renderer's basis: fit and render agree
from .features import (DEFAULT_FEATURE_DIM, default_features_at, projection_matrix, sample_client_features,
                       sample_client_labels)
from .registration import registration_weight
from .reliability import AppearanceUncertainty, positional_uncertainty

if TYPE_CHECKING:  # the settings are read, never constructed, here; importing the scene package would run it
    from ..config import SceneConfig


@dataclass
class FrameEvidence:
    """Per-observation evidence of one frame, only at pixels with valid depth, in row-major order.

    Attributes:
        rows, cols: [M] int64 pixel coordinates (v, u).
        points: [M, 3] float32 lifted world points x = Pi^-1(m, D(m)).
        colors: [M, 3] float32 RGB in [0, 1].
        features: [M, L] float32 F_view.
        u_pos: [M] float32 positional uncertainty in voxel units.
        reliability: [M] float32 R_view in (0, 1].
        labels: optional [M, S] float32 label scores.
    """

    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    features: np.ndarray
    u_pos: np.ndarray
    reliability: np.ndarray
    labels: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.rows.shape[0])


@numba.njit(parallel=True, cache=True)
def valid_depth_pixels(depth, near, far):  # [H, W] float32 -> rows [M], cols [M] int64, row-major
    """Pixels whose depth lies in (near, far): np.nonzero of the mask without [H, W] temporaries,
    rows counted and filled in parallel (each row's pixels land at its prefix-sum offset)."""
    H, W = depth.shape
    first = np.zeros(H + 1, np.int64)
    for v in numba.prange(H):
        n = 0
        for u in range(W):
            n += near < depth[v, u] < far
        first[v + 1] = n
    for v in range(H):
        first[v + 1] += first[v]
    rows = np.empty(first[H], np.int64)
    cols = np.empty(first[H], np.int64)
    for v in numba.prange(H):
        k = first[v]
        for u in range(W):
            if near < depth[v, u] < far:
                rows[k], cols[k] = v, u
                k += 1
    return rows, cols


@numba.njit(parallel=True, cache=True)
def _lift_kernel(rgb, depth, rows, cols, fx, fy, cx, cy, R, t, points, colors):
    for i in numba.prange(rows.shape[0]):
        v, u = rows[i], cols[i]
        z = depth[v, u]
        xc = (np.float32(u) - cx) / fx * z
        yc = (np.float32(v) - cy) / fy * z
        for a in range(3):
            points[i, a] = R[a, 0] * xc + R[a, 1] * yc + R[a, 2] * z + t[a]
            colors[i, a] = np.float32(rgb[v, u, a]) / np.float32(255.0)


def lift_pixels(frame: Frame, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [M, 3] and colours [M, 3] of the given pixels (numba; same maths as Camera.lift)."""
    cam = frame.camera
    c2w = cam.c2w.numpy()
    points = np.empty((rows.shape[0], 3), np.float32)
    colors = np.empty((rows.shape[0], 3), np.float32)
    _lift_kernel(frame.rgb.numpy(), frame.depth.numpy(), rows, cols, np.float32(cam.fx), np.float32(cam.fy),
                 np.float32(cam.cx), np.float32(cam.cy), np.ascontiguousarray(c2w[:3, :3]),
                 np.ascontiguousarray(c2w[:3, 3]), points, colors)
    return points, colors


def check_client_features(frame: Frame, config: SceneConfig) -> None:
    """A frame's client features as a session with ``features.backend`` ``client`` takes them: there,
    with the session's channels (`FeatureSettings.client_channels`). ValueError naming ``features``."""
    if config.features.backend != "client":
        return
    if frame.features is None:
        raise ValueError("features: this session uses client-supplied features, but the frame carries none")
    expected, got = config.features.client_channels, int(frame.features.shape[-1])
    if expected is not None and got != expected:
        raise ValueError(f"features: expected {expected} channels a pixel (this session's, its first frame's), got {got}")


def frame_features(frame: Frame, rows: np.ndarray, cols: np.ndarray, config: SceneConfig) -> np.ndarray:  # [M, L]
    """F_view at the given pixels from the configured backend, with ``config.features.dim`` channels."""
    if config.features.backend == "client":
        check_client_features(frame, config)
        feats = sample_client_features(frame.features.numpy(), rows, cols, (frame.height, frame.width))
    else:
        feats = default_features_at(frame.rgb.numpy(), rows, cols)
    if feats.shape[1] != config.features.dim:
        feats = feats @ projection_matrix(feats.shape[1], config.features.dim)
    return np.ascontiguousarray(feats, dtype=np.float32)


def extract_evidence(
    frame: Frame,
    config: SceneConfig,
    appearance: AppearanceUncertainty | None = None,
) -> FrameEvidence:
    """Evidence of one frame with depth: every pixel whose depth lies in (near, far).

    Raises ValueError (naming the field) when the frame has no depth, or the session's feature
    backend needs client features the frame does not carry.
    """
    if frame.depth is None:
        raise ValueError("depth: this frame has no depth; RGB-only frames need the multi-view depth stage")
    depth = frame.depth.numpy()
    sensor = config.sensor.in_effect(depth)  # a scene's own choice; outside one, this frame's family
    rows, cols = valid_depth_pixels(depth, np.float32(config.range.near), np.float32(config.range.far))
    features = frame_features(frame, rows, cols, config)
    points, colors = lift_pixels(frame, rows, cols)
    u_pos = positional_uncertainty(
        depth, rows, cols, config.voxel_size,
        depth_std=None if frame.depth_std is None else frame.depth_std.numpy(),
        sigma0=sensor.sigma0, sigma2=sensor.sigma2, z_ref=sensor.sigma_ref, edge_weight=sensor.edge_weight,
    )
    log_r = -u_pos
    if sensor.registration_px > 0:
        log_r = log_r + np.log(registration_weight(depth, rows, cols, sensor.registration_px, config.voxel_size,
                                                   sensor.sigma0, sensor.sigma2, sensor.sigma_ref))
    if appearance is not None and not appearance.is_zero:
        with torch.no_grad():
            log_r = log_r - appearance(torch.from_numpy(features)).numpy()
    labels = sample_client_labels(frame, rows, cols)
    return FrameEvidence(
        rows=rows, cols=cols, points=points, colors=colors, features=features, u_pos=u_pos,
        reliability=np.exp(log_r).astype(np.float32), labels=labels,
    )


def observation_sh_basis(evidence: FrameEvidence, camera, degree: int) -> np.ndarray:  # [M, (degree + 1)^2]
    """SH basis of each observation's view direction (camera centre -> lifted point), 3DGS convention.

    Degree 0 needs no basis (no view dependence): it returns an all-zero [M, 1] placeholder."""
    if degree == 0:
        return np.zeros((len(evidence), 1), np.float32)
    return sh_basis_at_points(evidence.points, camera.center.numpy(), degree)


__all__ = ["FrameEvidence", "extract_evidence", "lift_pixels", "frame_features", "observation_sh_basis", "DEFAULT_FEATURE_DIM"]
