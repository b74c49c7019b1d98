"""Pictures of rendered maps that a person can look at (feature splats as RGB)."""

from __future__ import annotations

import numpy as np


def feature_preview(
    features: np.ndarray,  # [H, W, C] composited feature sums (as `render` returns them)
    alpha: np.ndarray,  # [H, W] accumulated opacity
) -> np.ndarray:  # [H, W, 3] uint8
    """PCA of the covered pixels' features onto 3 channels, each stretched to its 1st-99th percentile.

    Composited sums are divided by alpha first, so the picture shows what the features say, not how
    opaque the pixel is. Uncovered pixels are black.

    Example:
        >>> f = np.random.default_rng(0).standard_normal((4, 5, 8)).astype(np.float32)
        >>> feature_preview(f, np.ones((4, 5), np.float32)).shape
        (4, 5, 3)
    """
    if features.ndim != 3 or alpha.shape != features.shape[:2]:
        raise ValueError(f"features: expected [H, W, C] with alpha [H, W], got {list(features.shape)} and {list(alpha.shape)}")
    h, w, c = features.shape
    covered = alpha > 1e-3
    out = np.zeros((h, w, 3), np.uint8)
    if covered.sum() < 2:
        return out
    f = features[covered].astype(np.float64) / alpha[covered, None]
    f -= f.mean(0)
    _, _, vt = np.linalg.svd(f[:: max(1, len(f) // 20000)], full_matrices=False)  # a subsample fixes the axes
    proj = f @ vt[: min(3, c)].T
    if proj.shape[1] < 3:
        proj = np.pad(proj, ((0, 0), (0, 3 - proj.shape[1])))
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    scaled = (proj - lo) / np.where(hi > lo, hi - lo, 1.0)
    out[covered] = np.clip(np.round(scaled * 255.0), 0, 255).astype(np.uint8)
    return out
