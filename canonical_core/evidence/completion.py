"""Depth completion: the large holes of sensor depth (`sensor_holes`) filled from the plane sweep
(`complete_depth`), sensor pixels never changed.
"""

from __future__ import annotations

import numpy as np


def sensor_holes(
    depth: np.ndarray,  # [H, W] float32 sensor depth, 0 = missing
    radius: int,
) -> np.ndarray:  # [H, W] bool
    """The pixels with no measured depth within ``radius`` pixels (a square window): the regions a
    depth sensor does not reach (beyond its range, outside its field of view, dark or specular
    surfaces), not the small regular holes of its pattern, which voxels bridge anyway.

    Example:
        >>> d = np.zeros((3, 8), np.float32); d[:, :2] = 1.0
        >>> sensor_holes(d, radius=2)[0].astype(int).tolist()
        [0, 0, 0, 0, 1, 1, 1, 1]
    """
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 1:
        raise ValueError(f"radius: expected a positive integer, got {radius!r}")
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise ValueError(f"depth: expected an [H, W] array, got {list(getattr(depth, 'shape', []))}")
    measured = (depth > 0).astype(np.int32)
    return _window_sum(_window_sum(measured, radius, 0), radius, 1) == 0


def _window_sum(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """Sums of ``a`` over windows [i - radius, i + radius] along ``axis`` (clipped at the borders),
    from one cumulative sum: the cost does not grow with the radius."""
    n = a.shape[axis]
    c = np.cumsum(a, axis=axis, dtype=np.int32)  # counts of at most H * W pixels
    c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
    i = np.arange(n)
    return np.take(c, np.minimum(i + radius + 1, n), axis=axis) - np.take(c, np.maximum(i - radius, 0), axis=axis)


def complete_depth(
    depth: np.ndarray,  # [H, W] float32 sensor depth, metres, 0 = missing
    depth_std: np.ndarray,  # [H, W] float32 the sensor depth's std, metres
    estimate: np.ndarray,  # [H, W] float32 swept depth (`estimate_depth`), 0 = none
    uncertainty: np.ndarray,  # [H, W] float32 its U_pos, metres
    holes: np.ndarray,  # [H, W] bool: the pixels to fill (`sensor_holes`)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # depth [H, W], std [H, W] float32, filled [H, W] bool
    """Sensor depth with its large holes filled from the plane sweep.

    A pixel is filled when it is one of ``holes`` and the sweep gives it a depth. Filled pixels carry
    the sweep's U_pos as their std, so their reliability is as low as the sweep is unsure; sensor
    pixels are never changed. Sweep depth is a few voxels off where sensor depth is within one, so
    where earlier frames measured the same surface the fill adds a less exact copy of it (depth
    agreement falls a little). Only the holes need a sweep: ``estimate_depth(..., where=holes)``.

    Example:
        >>> d = np.zeros((5, 9), np.float32); d[:, :3] = 1.0
        >>> est = np.full((5, 9), 2.0, np.float32)
        >>> out, std, filled = complete_depth(d, np.full_like(d, 0.01), est, np.full_like(d, 0.1), sensor_holes(d, 2))
        >>> filled[0].astype(int).tolist(), out[0].tolist()
        ([0, 0, 0, 0, 0, 1, 1, 1, 1], [1.0, 1.0, 1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 2.0])
    """
    shape = depth.shape
    for name, value in (("depth_std", depth_std), ("estimate", estimate), ("uncertainty", uncertainty), ("holes", holes)):
        if value.shape != shape:
            raise ValueError(f"{name}: expected shape {list(shape)} (as depth), got {list(value.shape)}")
    if holes.dtype != np.bool_:
        raise ValueError(f"holes: expected a bool array, got {holes.dtype}")
    filled = holes & (depth <= 0) & (estimate > 0)
    out = np.where(filled, estimate, depth).astype(np.float32)
    std = np.where(filled, uncertainty, depth_std).astype(np.float32)
    return out, std, filled

