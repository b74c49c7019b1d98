"""The web viewer: static pages (``static/``: HTML, CSS, ES modules, no build step) and the pictures
the viewer's image route draws from rendered maps (depth colour-mapped, coverage, label colours).

Example:
    >>> import numpy as np
    >>> depth_picture(np.array([[1.0, 2.0]], np.float32), np.ones((1, 2), np.float32), (1.0, 2.0))[0].tolist()
    [[250, 231, 80], [14, 10, 64]]
"""

from __future__ import annotations

from importlib import resources

import numpy as np

from ..wire import LABEL_PALETTE

STATIC = resources.files(__package__) / "static"

# Depth colour map, near (index 0) to far (index 255): bright warm to dark cool, with lightness
# falling monotonically so that the order of depths reads off the brightness too.
DEPTH_STOPS = np.array([(250, 231, 80), (236, 142, 52), (196, 70, 86), (122, 40, 122), (60, 36, 120), (14, 10, 64)], np.float64)
UNCOVERED = (12, 12, 16)  # where nothing is drawn (alpha below COVERED)
COVERED = 0.05
# Coverage: where little is drawn (film there next) is magenta, fully covered is light grey.
SPARSE, DENSE = np.array((200, 20, 140), np.float64), np.array((225, 225, 225), np.float64)
PALETTE = np.array(LABEL_PALETTE, np.uint8).reshape(256, 3)  # index 0 none, k + 1 label k (the label PNG's palette)


def depth_lut(n: int = 256) -> np.ndarray:  # [n, 3] uint8
    """The depth colour map as ``n`` colours, piecewise linear through `DEPTH_STOPS`."""
    t = np.linspace(0.0, len(DEPTH_STOPS) - 1, n)
    i = np.minimum(t.astype(int), len(DEPTH_STOPS) - 2)
    f = (t - i)[:, None]
    return np.round(DEPTH_STOPS[i] * (1 - f) + DEPTH_STOPS[i + 1] * f).astype(np.uint8)


DEPTH_LUT = depth_lut()


def depth_range(depth: np.ndarray, alpha: np.ndarray) -> tuple[float, float]:
    """The 2nd-98th percentile of the drawn depths (a stable scale that ignores a few floaters);
    (0, 1) where nothing is drawn."""
    d = depth[(alpha > COVERED) & (depth > 0)]
    if d.size == 0:
        return 0.0, 1.0
    near, far = np.percentile(d, [2, 98])
    return float(near), float(max(far, near + 1e-6))


def centre_depth(depth: np.ndarray, alpha: np.ndarray) -> float | None:
    """Median depth drawn in the middle ninth of the view (the middle third of each side); None
    where nothing is drawn there."""
    h, w = depth.shape
    d, a = depth[h // 3 : h - h // 3, w // 3 : w - w // 3], alpha[h // 3 : h - h // 3, w // 3 : w - w // 3]
    drawn = d[(a > COVERED) & (d > 0)]
    return float(np.median(drawn)) if drawn.size else None


def depth_picture(
    depth: np.ndarray,  # [H, W] float depth along the optical axis (0 where nothing is drawn)
    alpha: np.ndarray,  # [H, W] accumulated opacity
    near_far: tuple[float, float],
) -> np.ndarray:  # [H, W, 3] uint8
    """Depth through `DEPTH_LUT`, ``near`` -> index 0, ``far`` -> index 255 (clamped beyond)."""
    near, far = near_far
    if not (np.isfinite(near) and np.isfinite(far) and far > near):
        raise ValueError(f"depth_range: far must exceed near (both finite), got {near}, {far}")
    # float64: a float32 difference of two nearby ranges can be 0 (0 / 0 is no index)
    scaled = (depth.astype(np.float64) - near) * (255.0 / (far - near))
    index = np.clip(np.round(np.nan_to_num(scaled, nan=0.0)), 0, 255).astype(np.intp)
    out = DEPTH_LUT[index]
    out[(alpha <= COVERED) | (depth <= 0)] = UNCOVERED
    return out


def coverage_picture(alpha: np.ndarray) -> np.ndarray:  # [H, W] -> [H, W, 3] uint8
    """Accumulated opacity from magenta (nothing drawn: film here) to light grey (fully covered)."""
    a = np.clip(alpha, 0.0, 1.0)[..., None]
    return np.round(SPARSE * (1 - a) + DENSE * a).astype(np.uint8)


def label_picture(labels: np.ndarray) -> np.ndarray:  # [H, W] int (-1 none) -> [H, W, 3] uint8
    """Label k in the label PNG's palette colour k + 1, black where none; labels past 254 (the palette
    holds 255 labels) take the colours of those 255 below them, never black, which says nothing is drawn."""
    labels = labels.astype(np.int64)
    return PALETTE[np.where(labels < 0, 0, 1 + labels % 255)]


def visible_labels(labels: np.ndarray) -> list[int]:
    """The label ids drawn somewhere in ``labels`` (int [H, W], -1 none), ascending."""
    ids = np.unique(labels)
    return [int(k) for k in ids if k >= 0]
