"""Open3D VoxelBlockGrid TSDF fusion: the classical peer for benchmarks and evaluation.

Optional: needs the `bench` extra (``open3d-cpu``; on Debian it also needs ``libusb-1.0-0``).
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..frame import Frame


def open3d_available() -> bool:
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError):  # OSError: the wheel's shared libraries (libusb) are missing
        return False
    return True


class Open3DTSDF:
    """TSDF + colour in an Open3D VoxelBlockGrid (block resolution 16, truncation 8 voxels, as the
    Open3D reconstruction examples use), integrated frame by frame."""

    def __init__(self, voxel_size: float, depth_max: float = 3.0, block_count: int = 40_000):
        import open3d as o3d
        import open3d.core as o3c

        self._o3d, self._o3c = o3d, o3c
        self.voxel_size, self.depth_max = voxel_size, depth_max
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=voxel_size,
            block_resolution=16,
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
        blocks = self.grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, self.depth_max)
        self.grid.integrate(blocks, depth, color, intrinsic, extrinsic, 1.0, self.depth_max)

    def voxel_count(self) -> int:
        return int(self.grid.hashmap().size()) * 16**3
