"""Intrinsics and poses as numpy arrays: their checks, quaternions, the OpenGL axis flip.

Numpy only, no torch: capture loaders list a capture's frames and poses with these, and a client
that sends a capture's files as they are (`canonical stream`) starts without loading torch.
`camera.Camera` validates its inputs with the same checks.

Example:
    >>> import numpy as np
    >>> validate_pose(np.eye(4)).dtype, quaternion_to_matrix([1.0, 0.0, 0.0, 0.0]).tolist()[0]
    (dtype('float64'), [1.0, 0.0, 0.0])
    >>> validate_intrinsics([[500, 0, 320], [0, -500, 240], [0, 0, 1]])
    Traceback (most recent call last):
        ...
    ValueError: K: focal lengths must be positive, got fx=500, fy=-500
"""

from __future__ import annotations

import sys

import numpy as np

ROTATION_TOLERANCE = 1e-3
# Bounds that separate a real camera from numbers that are finite but absurd: the focal length in
# units of the image's larger side (a field of view between about 0.06 and 179.9 degrees), and the
# largest coordinate a pose may reach in scene units (beyond it float32 positions, as the fold and
# the renderer keep them, are coarser than one unit).
MIN_FOCAL_PER_SIDE = 1e-3
MAX_FOCAL_PER_SIDE = 1e3
MAX_TRANSLATION = 1e7
# A view's principal point may lie outside its image (a crop or a tile of a larger view), but not
# more than this many image sides away from it.
MAX_PRINCIPAL_OFFSET = 4.0

# OpenGL/NeRF camera axes (x right, y up, z backward) -> OpenCV axes (x right, y down, z forward).
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def as_float64(value, field: str) -> np.ndarray:
    """``value`` (lists, numpy, a torch tensor) as a float64 array; ValueError naming ``field`` if not numeric."""
    torch = sys.modules.get("torch")  # a tensor can only come from a torch that is loaded already
    if torch is not None and isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{field}: expected a numeric array, got {type(value).__name__} ({exc})") from None
    return array


def validate_intrinsics(K, field: str = "K") -> np.ndarray:
    """Check a 3x3 pinhole matrix and return it as float64.

    Raises ValueError naming ``field`` for a wrong shape, non-finite values, a non-positive focal
    length, skew or a bottom row other than [0, 0, 1].
    """
    K = as_float64(K, field)
    if K.shape != (3, 3):
        raise ValueError(f"{field}: expected shape [3, 3], got {list(K.shape)}")
    if not np.isfinite(K).all():
        raise ValueError(f"{field}: contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"{field}: focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}")
    if K[0, 1] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise ValueError(f"{field}: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    return K


def validate_pose(c2w, field: str = "c2w") -> np.ndarray:
    """Check a 4x4 rigid transform and return it as float64.

    Raises ValueError naming ``field`` for a wrong shape, NaN/inf, a bottom row other than
    [0, 0, 0, 1], a rotation that is not orthonormal to 1e-3, or a determinant other than +1.
    """
    T = as_float64(c2w, field)
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise ValueError(f"{field}: expected shape [4, 4] (or [3, 4]), got {list(T.shape)}")
    if not np.isfinite(T).all():
        raise ValueError(f"{field}: contains NaN or inf")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError(f"{field}: bottom row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > ROTATION_TOLERANCE:
        raise ValueError(f"{field}: rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {ROTATION_TOLERANCE})")
    det = np.linalg.det(R)
    if det < 0:
        raise ValueError(f"{field}: rotation has determinant {det:.3f}; expected +1 (a reflection, not a rotation)")
    reach = np.abs(T[:3, 3]).max()
    if reach > MAX_TRANSLATION:
        raise ValueError(f"{field}: translation {T[:3, 3].tolist()} exceeds {MAX_TRANSLATION:g} in a coordinate")
    return T


def validate_image_intrinsics(K: np.ndarray, width: int, height: int, field: str = "K", margin: float = MAX_PRINCIPAL_OFFSET) -> None:
    """Check a validated ``K`` against its image size: the focal lengths within
    [MIN_FOCAL_PER_SIDE, MAX_FOCAL_PER_SIDE] x the larger side, and the principal point at most
    ``margin`` image sides outside the image (0: inside it). Raises ValueError naming ``field``."""
    side = max(width, height)
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not MIN_FOCAL_PER_SIDE * side <= f <= MAX_FOCAL_PER_SIDE * side:
            raise ValueError(f"{field}: {name}={f:g} pixels is not within [{MIN_FOCAL_PER_SIDE:g}, {MAX_FOCAL_PER_SIDE:g}] "
                             f"x the image side {side}")
    cx, cy = K[0, 2], K[1, 2]
    pad_x, pad_y = margin * width, margin * height
    if not (-0.5 - pad_x <= cx <= width - 0.5 + pad_x and -0.5 - pad_y <= cy <= height - 0.5 + pad_y):
        where = "outside the image" if margin == 0 else f"more than {margin:g} image sides outside the image"
        raise ValueError(f"{field}: principal point ({cx:g}, {cy:g}) lies {where} ({width}x{height}); "
                         f"is K for another image size?")


def quaternion_to_matrix(q) -> np.ndarray:
    """Unit quaternion (w, x, y, z), scalar first, [..., 4] -> rotation matrices [..., 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
