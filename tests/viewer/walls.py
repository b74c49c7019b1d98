"""A synthetic scene for the viewer tests: two fronto-parallel walls at known depths (the left half
of the image near, the right half far), coloured and labelled."""

from __future__ import annotations

import numpy as np

W, H, F = 128, 96, 100.0
NEAR, FAR = 1.0, 2.0  # the left half of the image sees a wall at NEAR, the right half one at FAR
LABELS = (0, 2)  # left wall label 0, right wall label 2 (of 3 channels)


def wall_frames() -> list[dict]:
    """Two frames (a small sideways step) of two fronto-parallel walls, coloured and labelled."""
    depth = np.full((H, W), FAR, np.float32)
    depth[:, : W // 2] = NEAR
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, : W // 2] = (200, 60, 40)
    rgb[:, W // 2 :] = (40, 80, 200)
    labels = np.zeros((H, W, 3), np.float32)
    labels[:, : W // 2, LABELS[0]] = 1.0
    labels[:, W // 2 :, LABELS[1]] = 1.0
    K = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]])
    frames = []
    for dx in (0.01, 0.0):
        c2w = np.eye(4)
        c2w[0, 3] = dx
        frames.append({"rgb": rgb, "depth": depth, "labels": labels, "K": K, "c2w": c2w})
    return frames
