"""Pinhole cameras in OpenCV axes (x right, y down, z forward), camera-to-world poses.

Conventions (see DESIGN.md): ``K`` is in pixels, pixel (u, v) is column u, row v with its centre
at (u, v); ``c2w`` maps camera coordinates to world coordinates. Poses are validated: finite,
rotation orthonormal to 1e-3, determinant +1.

Example:
    >>> import torch
    >>> cam = Camera(K=[[500, 0, 320], [0, 500, 240], [0, 0, 1]], c2w=torch.eye(4), width=640, height=480)
    >>> uv, z = cam.project(cam.lift(torch.tensor([[320.0, 240.0]]), torch.tensor([2.0])))
    >>> uv.tolist(), z.tolist()
    ([[320.0, 240.0]], [2.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .calibration import (OPENGL_TO_OPENCV, as_float64, quaternion_to_matrix, validate_image_intrinsics,
                          validate_intrinsics, validate_pose)
from .resample import resized_intrinsics


@dataclass(frozen=True, eq=False)
class Camera:
    """A validated pinhole camera.

    Attributes:
        K: intrinsics, float32 [3, 3] (fx, fy, cx, cy in pixels).
        c2w: camera-to-world pose, float32 [4, 4], OpenCV axes.
        width, height: image size in pixels.

    Construct from anything array-like (lists, numpy, torch); inputs are validated and stored as
    float32 tensors. The float64 originals are kept for geometry that needs the precision.
    """

    K: Tensor  # [3, 3]
    c2w: Tensor  # [4, 4]
    width: int
    height: int

    def __init__(self, K, c2w, width: int, height: int):
        K64 = validate_intrinsics(K)
        T64 = validate_pose(c2w)
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{name}: expected a positive integer, got {value!r}")
        validate_image_intrinsics(K64, int(width), int(height))
        object.__setattr__(self, "K", torch.from_numpy(K64.astype(np.float32)))
        object.__setattr__(self, "c2w", torch.from_numpy(T64.astype(np.float32)))
        object.__setattr__(self, "width", int(width))
        object.__setattr__(self, "height", int(height))
        object.__setattr__(self, "_K64", K64)
        object.__setattr__(self, "_c2w64", T64)

    # -- constructors -------------------------------------------------------------------------
    @classmethod
    def from_w2c(cls, K, w2c, width: int, height: int) -> "Camera":
        """Build from a world-to-camera (view) matrix."""
        w2c = validate_pose(w2c, "w2c")
        return cls(K, np.linalg.inv(w2c), width, height)

    @classmethod
    def from_opengl(cls, K, c2w_gl, width: int, height: int) -> "Camera":
        """Build from an OpenGL/NeRF camera-to-world pose (y up, z backward)."""
        return cls(K, validate_pose(c2w_gl, "c2w") @ OPENGL_TO_OPENCV, width, height)

    @classmethod
    def from_tum(cls, K, tum_pose, width: int, height: int) -> "Camera":
        """Build from a TUM pose line ``tx ty tz qx qy qz qw`` (camera-to-world, scalar last)."""
        p = as_float64(tum_pose, "pose")
        if p.shape != (7,):
            raise ValueError(f"pose: expected 7 values tx ty tz qx qy qz qw, got shape {list(p.shape)}")
        if not np.isfinite(p).all() or np.linalg.norm(p[3:]) < 1e-8:
            raise ValueError(f"pose: expected finite values and a non-zero quaternion, got {p.tolist()}")
        T = np.eye(4)
        T[:3, :3] = quaternion_to_matrix(np.array([p[6], p[3], p[4], p[5]]))
        T[:3, 3] = p[:3]
        return cls(K, T, width, height)

    # -- derived ------------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self._K64[0, 0])

    @property
    def fy(self) -> float:
        return float(self._K64[1, 1])

    @property
    def cx(self) -> float:
        return float(self._K64[0, 2])

    @property
    def cy(self) -> float:
        return float(self._K64[1, 2])

    @property
    def w2c(self) -> Tensor:  # [4, 4]
        """World-to-camera (view) matrix, float32."""
        return torch.from_numpy(np.linalg.inv(self._c2w64).astype(np.float32))

    @property
    def center(self) -> Tensor:  # [3]
        """Camera centre in world coordinates."""
        return self.c2w[:3, 3].clone()

    def K64(self) -> np.ndarray:  # [3, 3]
        return self._K64.copy()

    def c2w64(self) -> np.ndarray:  # [4, 4]
        return self._c2w64.copy()

    def scaled(self, factor: float) -> "Camera":
        """The same camera for its image resized by about ``factor``: to round(width x factor) x
        round(height x factor) pixels, each axis by the factor its rounded size makes (`resized`), so
        that the image's edges stay its edges and pixel centres stay consistent.

        Example:
            >>> cam = Camera([[500, 0, 32], [0, 500, 24], [0, 0, 1]], np.eye(4), 65, 49)
            >>> half = cam.scaled(0.5)
            >>> (half.width, half.height), half.K64()[0].tolist()
            ((32, 24), [246.15384615384616, 0.0, 15.5])
        """
        if isinstance(factor, bool) or not isinstance(factor, (int, float, np.integer, np.floating)) or not factor > 0:
            raise ValueError(f"factor: expected a positive number, got {factor!r}")
        return self.resized(max(1, int(round(self.width * factor))), max(1, int(round(self.height * factor))))

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for its image resized to ``width`` x ``height`` (each axis by its own
        factor; pixel centres stay consistent).

        Example:
            >>> cam = Camera([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], np.eye(4), 640, 480)
            >>> cam.resized(256, 192).K64()[:2].tolist()
            [[200.0, 0.0, 127.5], [0.0, 200.0, 95.5]]
        """
        if min(width, height) < 1:
            raise ValueError(f"width, height: expected positive sizes, got {width}x{height}")
        return Camera(self._resized_K(width / self.width, height / self.height), self._c2w64, width, height)

    def _resized_K(self, sx: float, sy: float) -> np.ndarray:  # [3, 3]
        return resized_intrinsics(self._K64, sx, sy)  # the rule the SDK applies to a frame it resizes

    def with_pose(self, c2w) -> "Camera":
        return Camera(self._K64, c2w, self.width, self.height)

    # -- geometry -----------------------------------------------------------------------------
    def lift(
        self,
        uv: Tensor,  # [N, 2] pixel coordinates (u = column, v = row)
        depth: Tensor,  # [N] z-depth along the optical axis
    ) -> Tensor:  # [N, 3] world points
        """Back-project pixels with z-depth to world points: x = c2w (z K^-1 [u, v, 1])."""
        uv = torch.as_tensor(uv, dtype=torch.float32)
        depth = torch.as_tensor(depth, dtype=torch.float32)
        if uv.ndim != 2 or uv.shape[-1] != 2:
            raise ValueError(f"uv: expected shape [N, 2], got {list(uv.shape)}")
        if depth.shape != uv.shape[:1]:
            raise ValueError(f"depth: expected shape [{uv.shape[0]}], got {list(depth.shape)}")
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        pc = torch.stack([x, y, depth], -1)
        return pc @ self.c2w[:3, :3].T + self.c2w[:3, 3]

    def project(
        self,
        points: Tensor,  # [N, 3] world points
    ) -> tuple[Tensor, Tensor]:  # uv [N, 2], z [N]
        """Project world points: returns pixel coordinates and z-depth (<= 0 means behind)."""
        points = torch.as_tensor(points, dtype=torch.float32)
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"points: expected shape [N, 3], got {list(points.shape)}")
        w2c = self.w2c
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        u = pc[:, 0] / safe * self.fx + self.cx
        v = pc[:, 1] / safe * self.fy + self.cy
        return torch.stack([u, v], -1), z

    def pixel_rays(self) -> Tensor:  # [H, W, 3]
        """Camera-frame directions with z = 1 for every pixel centre (row-major)."""
        v, u = torch.meshgrid(
            torch.arange(self.height, dtype=torch.float32),
            torch.arange(self.width, dtype=torch.float32),
            indexing="ij",
        )
        return torch.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, torch.ones_like(u)], -1)

    def __repr__(self) -> str:
        return (
            f"Camera({self.width}x{self.height}, fx={self.fx:.2f}, fy={self.fy:.2f}, "
            f"cx={self.cx:.2f}, cy={self.cy:.2f}, center={self._c2w64[:3, 3].round(4).tolist()})"
        )
