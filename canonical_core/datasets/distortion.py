"""OpenCV radial-tangential lens distortion: distort / undistort points, and undistort images.

The model (OpenCV ``k1 k2 p1 p2 k3`` order) maps a normalized undistorted coordinate (x, y) =
((u - cx) / fx, (v - cy) / fy) to a distorted one:

    r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

An image is undistorted by inverse mapping: each output pixel's coordinate is distorted and the
input is sampled there, so every output pixel gets exactly one value and no holes appear. The
undistorted image keeps the input's K.

Example:
    >>> import numpy as np
    >>> xy = np.array([[0.3, -0.2]])
    >>> d = (-0.1, 0.02, 0.001, -0.002)
    >>> bool(np.allclose(undistort_points(distort_points(xy, d), d), xy, atol=1e-9))
    True
"""

from __future__ import annotations

from typing import Literal, Sequence

import numpy as np


def _coefficients(coeffs: Sequence[float]) -> tuple[float, float, float, float, float]:
    c = np.asarray(coeffs, dtype=np.float64).reshape(-1)
    if c.shape[0] not in (4, 5) or not np.isfinite(c).all():
        raise ValueError(f"coeffs: expected 4 or 5 finite numbers (k1, k2, p1, p2[, k3]), got {list(np.ravel(coeffs))}")
    k1, k2, p1, p2 = c[:4]
    k3 = c[4] if c.shape[0] == 5 else 0.0
    return float(k1), float(k2), float(p1), float(p2), float(k3)


def distort_points(
    xy: np.ndarray,  # [..., 2] normalized undistorted coordinates
    coeffs: Sequence[float],  # (k1, k2, p1, p2[, k3])
) -> np.ndarray:  # [..., 2] normalized distorted coordinates
    """Apply the OpenCV radial-tangential model to normalized coordinates."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[-1:] != (2,):
        raise ValueError(f"xy: expected shape [..., 2], got {list(xy.shape)}")
    k1, k2, p1, p2, k3 = _coefficients(coeffs)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], -1)


def undistort_points(
    xy: np.ndarray,  # [..., 2] normalized distorted coordinates
    coeffs: Sequence[float],  # (k1, k2, p1, p2[, k3])
    iterations: int = 20,
) -> np.ndarray:  # [..., 2] normalized undistorted coordinates
    """Invert `distort_points` by fixed-point iteration (as OpenCV does); exact to ~1e-9 for
    moderate distortion inside the image."""
    xy_d = np.asarray(xy, dtype=np.float64)
    if xy_d.shape[-1:] != (2,):
        raise ValueError(f"xy: expected shape [..., 2], got {list(xy_d.shape)}")
    k1, k2, p1, p2, k3 = _coefficients(coeffs)
    x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xy_d[..., 0] - dx) / radial
        y = (xy_d[..., 1] - dy) / radial
    return np.stack([x, y], -1)


def remap(
    image: np.ndarray,  # [H, W] or [H, W, C]
    u: np.ndarray,  # [H', W'] source column of each output pixel
    v: np.ndarray,  # [H', W'] source row of each output pixel
    mode: Literal["bilinear", "nearest"],
) -> np.ndarray:  # [H', W'] or [H', W', C], image's dtype
    """Sample ``image`` at (u, v) (pixel centres at integers); samples off the image are 0.

    ``bilinear`` treats each pixel as covering +-0.5 around its centre (edge pixels are held to the
    border); ``nearest`` copies one input pixel, so it never mixes values (use it for depth).
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image: expected shape [H, W] or [H, W, C], got {list(image.shape)}")
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if u.shape != v.shape:
        raise ValueError(f"u, v: expected equal shapes, got {list(u.shape)} and {list(v.shape)}")
    H, W = image.shape[:2]
    inside = (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)
    if mode == "nearest":
        ui = np.clip(np.floor(u + 0.5), 0, W - 1).astype(np.int64)
        vi = np.clip(np.floor(v + 0.5), 0, H - 1).astype(np.int64)
        out = image[vi, ui]
    elif mode == "bilinear":
        uc = np.clip(u, 0, W - 1)
        vc = np.clip(v, 0, H - 1)
        u0 = np.floor(uc).astype(np.int64)
        v0 = np.floor(vc).astype(np.int64)
        u1 = np.minimum(u0 + 1, W - 1)
        v1 = np.minimum(v0 + 1, H - 1)
        au = (uc - u0)[..., None] if image.ndim == 3 else uc - u0
        av = (vc - v0)[..., None] if image.ndim == 3 else vc - v0
        src = image.astype(np.float64)
        top = src[v0, u0] * (1 - au) + src[v0, u1] * au
        bottom = src[v1, u0] * (1 - au) + src[v1, u1] * au
        out = top * (1 - av) + bottom * av
        if np.issubdtype(image.dtype, np.integer):
            info = np.iinfo(image.dtype)
            out = np.clip(np.round(out), info.min, info.max)
        out = out.astype(image.dtype)
    else:
        raise ValueError(f"mode: expected 'bilinear' or 'nearest', got {mode!r}")
    mask = inside[..., None] if image.ndim == 3 else inside
    return np.where(mask, out, np.zeros((), image.dtype))


def undistort_image(
    image: np.ndarray,  # [H, W] or [H, W, C]
    K: np.ndarray,  # [3, 3] intrinsics of both the input and the output
    coeffs: Sequence[float],  # (k1, k2, p1, p2[, k3])
    mode: Literal["bilinear", "nearest"] = "bilinear",
) -> np.ndarray:  # same shape and dtype as image
    """Undistort an image taken through the OpenCV model into a pinhole image with the same K.

    Example:
        >>> import numpy as np
        >>> K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
        >>> img = np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8)
        >>> bool((undistort_image(img, K, (0, 0, 0, 0)) == img).all())
        True
    """
    image = np.asarray(image)
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K: expected shape [3, 3], got {list(K.shape)}")
    H, W = image.shape[:2]
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    xy = distort_points(np.stack([(u - cx) / fx, (v - cy) / fy], -1), coeffs)
    return remap(image, xy[..., 0] * fx + cx, xy[..., 1] * fy + cy, mode)
