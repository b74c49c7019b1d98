"""Open3D VoxelBlockGrid TSDF fusion: the classical peer for benchmarks and evaluation.

Optional: needs the `bench` extra (``open3d-cpu``; on Debian it also needs ``libusb-1.0-0``).

Ray casting: ``VoxelBlockGrid.ray_cast`` takes the block coordinates that bound the rays. Passing
``hashmap().key_tensor()`` is wrong: that is the whole key *buffer* (``capacity`` rows, most of them
never activated and holding garbage), which made Open3D estimate a range map for hundreds of
thousands of bogus blocks and crash. `Open3DTSDF.ray_cast` passes only the active blocks
(``active_buf_indices``) that lie in the target camera's frustum.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..frame import Frame

BLOCK_RESOLUTION = 16  # voxels per block edge
TRUNCATION_VOXELS = 8.0  # sdf truncation in voxels, as the Open3D reconstruction examples use
_CORNERS = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)  # [8, 3]


def open3d_available() -> bool:
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):  # OSError: the wheel's shared libraries (libusb) are missing
        return False
    return True


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

    def voxel_count(self) -> int:
        return int(self.grid.hashmap().size()) * BLOCK_RESOLUTION**3

    def active_blocks(self) -> np.ndarray:  # [B, 3] int32 block coordinates
        """Coordinates of the allocated blocks (not the whole key buffer, see the module docstring)."""
        hashmap = self.grid.hashmap()
        active = hashmap.active_buf_indices().to(self._o3c.int64)
        return hashmap.key_tensor()[active].numpy().reshape(-1, 3)

    def blocks_in_view(self, camera: Camera, near: float = 0.01) -> np.ndarray:  # [B', 3] int32
        """Active blocks with a corner in front of ``camera`` (beyond ``near``) whose projected
        corners' bounding box overlaps the image: a conservative frustum test."""
        keys = self.active_blocks()
        corners = (keys[:, None, :] + _CORNERS[None]) * (self.voxel_size * BLOCK_RESOLUTION)  # [B, 8, 3]
        w2c = np.linalg.inv(camera.c2w64())
        pc = corners @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[..., 2]
        front = z > near
        K = camera.K64()
        zs = np.where(front, z, 1.0)
        u = np.where(front, pc[..., 0] / zs * K[0, 0] + K[0, 2], np.nan)
        v = np.where(front, pc[..., 1] / zs * K[1, 1] + K[1, 2], np.nan)
        with np.errstate(invalid="ignore"):  # all-nan rows belong to blocks behind the camera
            keep = (front.any(1) & (np.nanmax(u, 1) >= -0.5) & (np.nanmin(u, 1) <= camera.width - 0.5)
                    & (np.nanmax(v, 1) >= -0.5) & (np.nanmin(v, 1) <= camera.height - 0.5))
        return np.ascontiguousarray(keys[keep])

    def ray_cast(
        self,
        camera: Camera,
        weight_threshold: float = 1.0,
        near: float = 0.01,
        range_map_down_factor: int = 8,
    ) -> tuple[Tensor, Tensor]:  # rgb [H, W, 3] in [0, 1], depth [H, W] (0 = no surface)
        """Colour and depth of the first zero crossing along each pixel's ray.

        ``weight_threshold`` is the integration weight (number of frames, here) a voxel needs to
        count as a surface; Open3D's default of 3 would render nothing from two input frames.
        """
        o3c = self._o3c
        h, w = camera.height, camera.width
        blocks = self.blocks_in_view(camera, near)
        if len(blocks) == 0:
            return torch.zeros(h, w, 3), torch.zeros(h, w)
        intrinsic, extrinsic = self._camera_tensors(camera)
        result = self.grid.ray_cast(
            o3c.Tensor(blocks), intrinsic, extrinsic, w, h, ["depth", "color"],
            depth_scale=1.0, depth_min=near, depth_max=self.depth_max, weight_threshold=weight_threshold,
            trunc_voxel_multiplier=TRUNCATION_VOXELS, range_map_down_factor=range_map_down_factor,
        )
        depth = torch.from_numpy(result["depth"].numpy().reshape(h, w).copy())
        rgb = torch.from_numpy(result["color"].numpy().reshape(h, w, 3).copy()).clamp(0.0, 1.0)
        hit = depth > 0
        return torch.where(hit[..., None], rgb, torch.zeros_like(rgb)), torch.where(hit, depth, torch.zeros_like(depth))
