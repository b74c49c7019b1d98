"""Start-up warm-up: load the compiled kernels before the first real request.

A fresh process pays extra on its first fold and first render even with numba's on-disk cache
warm: numba starts its threading runtime and registers its array library on the first
parallel call, and each kernel's machine code is loaded on its first call. A service pays that
once at start-up instead of on a user's first request.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from canonical_core import Camera, Frame, Scene, SceneConfig, render
from canonical_core.datasets.images import depth_from_uint16


def warm_up(num_threads: int | None = None) -> float:
    """Fold two small synthetic RGB-D frames of a plane (their depth converted from 16-bit sensor
    codes, as most frames arrive; the second one moved, so free space runs against the first) into a
    scene that keeps undo records (as a session with a frame archive does), decode the scene after
    each fold (its colours solved: the background solve's kernels load too; the second decode
    reuses rows, as every decode after a fold does), render every map once and roll the
    second fold back (a correction's first step). Returns the seconds it took.

    Example:
        >>> warm_up() > 0
        True
    """
    start = time.perf_counter()
    height, width = 24, 32
    K = [[30.0, 0.0, (width - 1) / 2], [0.0, 30.0, (height - 1) / 2], [0.0, 0.0, 1.0]]
    cameras = [Camera(K=K, c2w=np.array([[1, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float),
                      width=width, height=height) for x in (0.0, 0.05)]
    depth = torch.from_numpy(depth_from_uint16(np.full((height, width), 1000, np.uint16), 1000.0))  # 1 m
    scene = Scene(SceneConfig(voxel_size=0.05), undo_depth=1)
    for camera in cameras:
        rgb = torch.full((height, width, 3), 128, dtype=torch.uint8)
        scene.fold(Frame(rgb=rgb, camera=camera, depth=depth))
        gaussians = scene.decode()  # the second reuses the rows the second fold left alone
    render(gaussians, cameras[-1], outputs=("rgb", "depth", "alpha", "features"), num_threads=num_threads)
    scene.rollback(1)
    return time.perf_counter() - start
