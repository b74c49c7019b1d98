"""Depth far rougher than its noise model: detect it per frame, replace it by a local median.

Reliability alone cannot rescue such a frame: every pixel's depth-edge term is huge, so every
observation gets almost no reliability, and the frame's geometry is a fog of scattered voxels
that fusion can only hide, not place (`SceneConfig.depth.denoise_radius`; its effect under depth
noise is in docs/evaluation.md).

    roughness = median over valid pixels of |z - median of the valid 3x3 neighbourhood| / sigma
with sigma the frame's per-pixel std where it has one, else the sensor model `sensor_depth_std`.
Clean sensor depth scores below 1 (neighbours agree to the millimetre),
i.i.d. noise of std s about 0.5 s / sigma. Above `ROUGHNESS_LIMIT` the frame's depth is replaced by the median of the
valid depths in a (2 radius + 1)^2 window, and its std by the std of that median, 1.2533 x 1.4826
x MAD / sqrt(n) (MAD over the window, n valid samples); pixels with fewer than `MIN_SAMPLES` valid
neighbours lose their depth. Missing pixels stay missing: the median fills no holes.
"""

from __future__ import annotations

import numba
import numpy as np

from .reliability import sensor_depth_std

# Clean captures score below 1, noise that reliability already handles (a few sensor sigmas) stays
# below; noise of a few percent of the depth scores far above. A clean frame pays only the check; the
# median's cost is in bench/fold.py's denoising table.
ROUGHNESS_LIMIT = 4.0
MIN_SAMPLES = 5
ROUGHNESS_STRIDE = 4  # the check reads one pixel in every 4 x 4 block: a median needs no more
_MEDIAN_STD = 1.2533  # std of the median of n Gaussian samples / (std / sqrt(n)), large n
_MAD_STD = 1.4826  # Gaussian std / median absolute deviation


@numba.njit(cache=True)
def _window(depth, v, u, radius, buf):
    H, W = depth.shape
    n = 0
    for vv in range(max(v - radius, 0), min(v + radius, H - 1) + 1):
        for uu in range(max(u - radius, 0), min(u + radius, W - 1) + 1):
            z = depth[vv, uu]
            if z > 0:
                buf[n] = z
                n += 1
    return n


@numba.njit(parallel=True, cache=True)
def _roughness_kernel(depth, sigma, stride, out):
    # out and sigma [ceil(H / stride), ceil(W / stride)]: one pixel per stride^2 block, the block's first
    for i in numba.prange(out.shape[0]):
        buf = np.empty(9, np.float32)
        for j in range(out.shape[1]):
            v, u = i * stride, j * stride
            out[i, j] = np.nan
            if depth[v, u] > 0:
                n = _window(depth, v, u, 1, buf)
                for a in range(1, n):  # insertion sort of <= 9 values: no allocation per pixel
                    x, b = buf[a], a - 1
                    while b >= 0 and buf[b] > x:
                        buf[b + 1] = buf[b]
                        b -= 1
                    buf[b + 1] = x
                med = buf[n // 2] if n % 2 else np.float32(0.5) * (buf[n // 2 - 1] + buf[n // 2])
                out[i, j] = abs(depth[v, u] - med) / max(sigma[i, j], np.float32(1e-9))


@numba.njit(parallel=True, cache=True)
def _median_kernel(depth, radius, min_samples, out_depth, out_std):
    H, W = depth.shape
    side = 2 * radius + 1
    for v in numba.prange(H):
        buf = np.empty(side * side, np.float32)
        dev = np.empty(side * side, np.float32)
        for u in range(W):
            out_depth[v, u] = 0.0
            out_std[v, u] = 0.0
            if depth[v, u] > 0:
                n = _window(depth, v, u, radius, buf)
                if n >= min_samples:
                    med = np.median(buf[:n])
                    for i in range(n):
                        dev[i] = abs(buf[i] - med)
                    out_depth[v, u] = med
                    out_std[v, u] = _MEDIAN_STD * _MAD_STD * np.median(dev[:n]) / np.sqrt(np.float32(n))


def depth_roughness(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    sigma: np.ndarray,  # [H, W] float32 metres, the noise the depth claims (> 0 where depth > 0)
    stride: int = ROUGHNESS_STRIDE,
) -> float:
    """Median over valid pixels of |z - median of its valid 3x3 neighbourhood| / sigma (module
    docstring), over every ``stride``-th pixel of every ``stride``-th row (a median needs no more,
    and the check runs on every frame); 0 for a frame without valid depth.

    Example:
        >>> depth = np.full((8, 8), 0.5, np.float32)
        >>> depth_roughness(depth, np.full((8, 8), 0.001, np.float32))
        0.0
    """
    if depth.ndim != 2 or sigma.shape != depth.shape:
        raise ValueError(f"sigma: expected the depth's shape {tuple(depth.shape)}, got {tuple(sigma.shape)}")
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride: expected a positive integer, got {stride!r}")
    return _roughness(depth, sigma[::stride, ::stride], stride)


def _roughness(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    sigma: np.ndarray,  # [ceil(H / stride), ceil(W / stride)]: the noise at the pixels the check reads
    stride: int,
) -> float:
    """`depth_roughness` with sigma given only where it is read (every ``stride``-th pixel of every
    ``stride``-th row), so that a frame without a per-pixel std evaluates its noise model there alone."""
    out = np.empty(sigma.shape, np.float32)
    _roughness_kernel(np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(sigma, np.float32), stride, out)
    valid = out[np.isfinite(out)]
    return float(np.median(valid)) if valid.size else 0.0


def median_depth(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    radius: int,
) -> tuple[np.ndarray, np.ndarray]:  # depth [H, W], std [H, W], float32 metres
    """The median of the valid depths in each valid pixel's (2 radius + 1)^2 window and that
    median's std (module docstring); pixels with fewer than `MIN_SAMPLES` valid samples get 0 (missing)."""
    if isinstance(radius, bool) or not isinstance(radius, int) or radius < 1:
        raise ValueError(f"radius: expected a positive integer, got {radius!r}")
    if depth.ndim != 2:
        raise ValueError(f"depth: expected [H, W], got shape {tuple(depth.shape)}")
    out_depth = np.empty(depth.shape, np.float32)
    out_std = np.empty(depth.shape, np.float32)
    _median_kernel(np.ascontiguousarray(depth, np.float32), radius, MIN_SAMPLES, out_depth, out_std)
    return out_depth, out_std


def denoise_rough_depth(
    depth: np.ndarray,  # [H, W] float32 metres, 0 = missing
    depth_std: np.ndarray | None,  # [H, W] float32 metres, or None for the sensor model
    radius: int,
    sigma0: float,
    sigma2: float,
    z_ref: float,
) -> tuple[np.ndarray, np.ndarray | None]:
    """(depth, depth_std) unchanged when the frame's roughness is at most `ROUGHNESS_LIMIT` (or
    ``radius`` is 0), else `median_depth` of it."""
    if radius == 0:
        return depth, depth_std
    read = (slice(None, None, ROUGHNESS_STRIDE),) * 2  # the pixels the check reads
    sigma = sensor_depth_std(depth[read], sigma0, sigma2, z_ref) if depth_std is None else depth_std[read]
    if _roughness(depth, sigma, ROUGHNESS_STRIDE) <= ROUGHNESS_LIMIT:
        return depth, depth_std
    return median_depth(depth, radius)


__all__ = ["ROUGHNESS_LIMIT", "MIN_SAMPLES", "depth_roughness", "median_depth", "denoise_rough_depth"]
