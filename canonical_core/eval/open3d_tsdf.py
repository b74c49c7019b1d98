"""Open3D VoxelBlockGrid TSDF fusion: the classical peer for benchmarks and evaluation.

Optional: needs the `bench` extra (``open3d-cpu``; on Debian it also needs ``libusb-1.0-0``).

Integration is Open3D's. Rendering casts rays through Open3D's TSDF voxels with our own numba
kernel (`ray_cast_tsdf`), using the rule of Open3D's ``VoxelBlockGrid.ray_cast``: march each pixel's
ray, skipping unallocated blocks and stepping by the truncated distance (at least one voxel); the
surface is the first crossing from a positive to a non-positive TSDF sample between two samples
whose weight reaches the threshold, at the linearly interpolated depth; its colour is the trilinear
interpolation of the voxel colours around it.

Why not ``VoxelBlockGrid.ray_cast`` (open3d 0.20): (1) passing ``hashmap().key_tensor()`` as the
block list hands it the whole key *buffer* (``capacity`` rows, most never activated and holding
garbage), which made it estimate a range map for hundreds of thousands of bogus blocks
("needed 371694 fragments") and crash; only ``active_buf_indices()`` rows are blocks. (2) Even with
the active blocks in the camera's frustum, whenever its fragment buffer is too small it
reallocates and that call returns an empty image, and on small images (80x60, 2 cm voxels) the
call never returned (known upstream: isl-org/Open3D#6821, #5344). A peer that may hang cannot run
unattended, so we read its voxels and cast the rays ourselves.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..frame import Frame

BLOCK_RESOLUTION = 16  # voxels per block edge
TRUNCATION_VOXELS = 8.0  # sdf truncation in voxels, as the Open3D reconstruction examples use
_KEY_BITS = 21  # block coordinates packed into one int64 key, 21 bits per axis
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


def open3d_import_error() -> str | None:
    """Why ``import open3d`` fails here (not installed, or the wheel's shared libraries such as
    libusb missing), or None when it works."""
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def open3d_available() -> bool:
    return open3d_import_error() is None


class Open3DTSDF:
    """TSDF + colour in an Open3D VoxelBlockGrid (block resolution 16, truncation 8 voxels, as the
    Open3D reconstruction examples use), integrated frame by frame.

    Args:
        voxel_size: voxel edge, metres.
        depth_max: depth beyond which measurements are ignored (and rays stop), metres.
        block_count: initial hash capacity in blocks, allocated up front (about 80 kB each); Open3D
            grows it (with a pause) when a frame needs more.
    """

    def __init__(self, voxel_size: float, depth_max: float = 3.0, block_count: int = 40_000):
        import open3d as o3d
        import open3d.core as o3c

        if not voxel_size > 0:
            raise ValueError(f"voxel_size: expected a positive number, got {voxel_size!r}")
        if not depth_max > 0:
            raise ValueError(f"depth_max: expected a positive number, got {depth_max!r}")
        self._o3d, self._o3c = o3d, o3c
        self.voxel_size, self.depth_max = voxel_size, depth_max
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=voxel_size,
            block_resolution=BLOCK_RESOLUTION,
            block_count=block_count,
            device=o3c.Device("CPU:0"),
        )
        self._volume: tuple[np.ndarray, ...] | None = None  # active voxels for ray casting, rebuilt after integrate

    def _camera_tensors(self, camera: Camera):
        o3c = self._o3c
        return (o3c.Tensor(camera.K64(), dtype=o3c.float64),
                o3c.Tensor(np.linalg.inv(camera.c2w64()), dtype=o3c.float64))

    def integrate(self, frame: Frame) -> None:
        if frame.depth is None:
            raise ValueError("depth: TSDF integration needs depth")
        o3d = self._o3d
        depth = o3d.t.geometry.Image(np.ascontiguousarray(frame.depth.numpy()))
        color = o3d.t.geometry.Image(np.ascontiguousarray(frame.rgb.numpy().astype(np.float32) / 255.0))
        intrinsic, extrinsic = self._camera_tensors(frame.camera)
        blocks = self.grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, self.depth_max,
                                                            TRUNCATION_VOXELS)
        self.grid.integrate(blocks, depth, color, intrinsic, extrinsic, 1.0, self.depth_max, TRUNCATION_VOXELS)
        self._volume = None

    def voxels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The allocated blocks, sorted by packed key: keys [B] int64, tsdf [B, 16, 16, 16] (in
        [-1, 1], truncation units), weight [B, 16, 16, 16], colour [B, 16, 16, 16, 3] in [0, 1] (Open3D
        stores float colour input times 255).
        Voxel (x, y, z) of block (bx, by, bz) is at [b, z, y, x] and sits at world point
        (16 bx + x, 16 by + y, 16 bz + z) * voxel_size (Open3D's layout)."""
        if self._volume is None:
            hashmap = self.grid.hashmap()
            active = hashmap.active_buf_indices().to(self._o3c.int64)  # only these key rows are blocks
            coords = hashmap.key_tensor()[active].numpy().reshape(-1, 3).astype(np.int64)
            keys = _pack_keys(coords)
            order = np.argsort(keys)
            r = BLOCK_RESOLUTION
            attr = {name: self.grid.attribute(name)[active].numpy() for name in ("tsdf", "weight", "color")}
            self._volume = (
                np.ascontiguousarray(keys[order]),
                np.ascontiguousarray(attr["tsdf"].reshape(-1, r, r, r)[order]),
                np.ascontiguousarray(attr["weight"].reshape(-1, r, r, r)[order]),
                np.ascontiguousarray(attr["color"].reshape(-1, r, r, r, 3)[order] / np.float32(255.0)),
            )
        return self._volume

    def ray_cast(
        self,
        camera: Camera,
        weight_threshold: float = 1.0,
        near: float = 0.01,
    ) -> tuple[Tensor, Tensor]:  # rgb [H, W, 3] in [0, 1], depth [H, W] (0 = no surface)
        """Colour and z-depth of the first surface along each pixel's ray (module docstring).

        ``weight_threshold`` is the integration weight (number of frames, here) both samples of a
        crossing need; Open3D's default of 3 would render nothing from two input frames.
        """
        h, w = camera.height, camera.width
        depth = np.zeros((h, w), np.float32)
        rgb = np.zeros((h, w, 3), np.float32)
        keys, tsdf, weight, color = self.voxels()
        if len(keys):
            c2w, K = camera.c2w64(), camera.K64()
            ray_cast_tsdf(keys, tsdf, weight, color, self.voxel_size, TRUNCATION_VOXELS * self.voxel_size,
                          np.ascontiguousarray(c2w[:3, 3]), np.ascontiguousarray(c2w[:3, :3]),
                          K[0, 0], K[1, 1], K[0, 2], K[1, 2], near, self.depth_max, weight_threshold, depth, rgb)
        return torch.from_numpy(rgb).clamp(0.0, 1.0), torch.from_numpy(depth)


def _pack_keys(coords: np.ndarray) -> np.ndarray:  # [B, 3] int64 block coordinates -> [B] int64
    c = coords + _KEY_OFFSET
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


@numba.njit(cache=True, inline="always")
def _find_block(keys, bx, by, bz) -> int:  # index into the sorted keys, or -1
    key = ((bx + _KEY_OFFSET) << (2 * _KEY_BITS)) | ((by + _KEY_OFFSET) << _KEY_BITS) | (bz + _KEY_OFFSET)
    i = np.searchsorted(keys, key)
    return i if i < keys.shape[0] and keys[i] == key else -1


@numba.njit(cache=True)
def _trilinear_color(keys, weight, color, px, py, pz, inv_voxel, out):  # out [3]; False if no voxel has weight
    r = BLOCK_RESOLUTION
    qx, qy, qz = px * inv_voxel, py * inv_voxel, pz * inv_voxel
    ix, iy, iz = math.floor(qx), math.floor(qy), math.floor(qz)
    fx, fy, fz = qx - ix, qy - iy, qz - iz
    total = 0.0
    acc0 = acc1 = acc2 = 0.0
    for k in range(8):
        dx, dy, dz = k & 1, (k >> 1) & 1, (k >> 2) & 1
        gx, gy, gz = ix + dx, iy + dy, iz + dz
        bx, by, bz = gx // r, gy // r, gz // r
        b = _find_block(keys, bx, by, bz)
        if b < 0:
            continue
        lx, ly, lz = gx - bx * r, gy - by * r, gz - bz * r
        if weight[b, lz, ly, lx] <= 0:
            continue
        f = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy) * (fz if dz else 1.0 - fz)
        acc0 += f * color[b, lz, ly, lx, 0]
        acc1 += f * color[b, lz, ly, lx, 1]
        acc2 += f * color[b, lz, ly, lx, 2]
        total += f
    if total <= 0.0:
        return False
    out[0], out[1], out[2] = acc0 / total, acc1 / total, acc2 / total
    return True


@numba.njit(parallel=True, cache=True)
def ray_cast_tsdf(keys, tsdf, weight, color, voxel, trunc, origin, rotation, fx, fy, cx, cy, t_near, t_far,
                  weight_threshold, out_depth, out_rgb):
    """Fill out_depth [H, W] (z-depth, 0 = no surface) and out_rgb [H, W, 3] by marching every pixel's
    ray through the sorted blocks (see `Open3DTSDF.voxels` for the layout and the module docstring
    for the rule). Rays are parametrised by z-depth t (direction with camera z = 1)."""
    r = BLOCK_RESOLUTION
    block = r * voxel
    inv_voxel = 1.0 / voxel
    h, w = out_depth.shape
    for v in numba.prange(h):
        col = np.empty(3)
        for u in range(w):
            xc, yc = (u - cx) / fx, (v - cy) / fy
            dx = rotation[0, 0] * xc + rotation[0, 1] * yc + rotation[0, 2]
            dy = rotation[1, 0] * xc + rotation[1, 1] * yc + rotation[1, 2]
            dz = rotation[2, 0] * xc + rotation[2, 1] * yc + rotation[2, 2]
            length = math.sqrt(dx * dx + dy * dy + dz * dz)  # world distance per unit of t
            t = t_near
            prev_ok = False
            prev_s = prev_t = 0.0
            while t < t_far:
                px, py, pz = origin[0] + t * dx, origin[1] + t * dy, origin[2] + t * dz
                gx, gy, gz = math.floor(px * inv_voxel), math.floor(py * inv_voxel), math.floor(pz * inv_voxel)
                bx, by, bz = gx // r, gy // r, gz // r
                b = _find_block(keys, bx, by, bz)
                if b < 0:  # unallocated block: jump to where the ray leaves it
                    t_exit = t_far
                    if dx != 0.0:
                        t_exit = min(t_exit, ((bx + (dx > 0)) * block - origin[0]) / dx)
                    if dy != 0.0:
                        t_exit = min(t_exit, ((by + (dy > 0)) * block - origin[1]) / dy)
                    if dz != 0.0:
                        t_exit = min(t_exit, ((bz + (dz > 0)) * block - origin[2]) / dz)
                    t = max(t_exit, t) + 1e-4 * voxel / length
                    prev_ok = False
                    continue
                lx, ly, lz = gx - bx * r, gy - by * r, gz - bz * r
                s = tsdf[b, lz, ly, lx]
                if weight[b, lz, ly, lx] < weight_threshold:
                    prev_ok = False
                    t += voxel / length
                    continue
                if prev_ok and prev_s > 0.0 and s <= 0.0:
                    hit = prev_t + (t - prev_t) * prev_s / (prev_s - s)
                    hx, hy, hz = origin[0] + hit * dx, origin[1] + hit * dy, origin[2] + hit * dz
                    out_depth[v, u] = hit
                    if _trilinear_color(keys, weight, color, hx, hy, hz, inv_voxel, col):
                        out_rgb[v, u, 0], out_rgb[v, u, 1], out_rgb[v, u, 2] = col[0], col[1], col[2]
                    break
                prev_ok, prev_s, prev_t = True, s, t
                t += max(voxel, s * trunc) / length
