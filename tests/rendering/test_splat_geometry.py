"""The EWA arithmetic shared by both CPU backends: torch and numba give bitwise-identical splats."""

from __future__ import annotations

import numpy as np
import torch

from canonical_core.rendering.projection import project_splats, world_to_camera
from canonical_core.rendering.splat_geometry import (
    CONIC_A, CONIC_B, CONIC_C, DEPTH, SPLAT_RECORD, U, V, project_numba, slope_bounds,
)  # fmt: skip

from .scenes import look_at_camera, random_scene


def test_torch_and_numba_projections_are_bitwise_identical():
    gaussians = random_scene(2000, 11, scale_range=(0.001, 0.8), opacity_range=(0.0, 1.0), spread=2.0)
    camera = look_at_camera(64, 48, 50.0, [0.3, -0.2, -2.5], [0.0, 0.1, 0.0], roll=0.3)
    # The fast path computes every Gaussian's splat without branches and drops the culled ones
    # after: Gaussians it must cull or keep exactly as the reference does.
    centre = torch.as_tensor(camera.c2w64()[:3, 3], dtype=torch.float32)
    gaussians.means[:4] = centre  # on the camera centre: z = 0
    gaussians.scales[4:8] = 1e20  # overflows float32 once squared
    gaussians.quats[8:12] = 0.0  # a zero rotation
    gaussians.opacities[12:16] = torch.tensor([0.0, 0.003, 0.0040, 0.2])  # below 1/255, just above, support < 9
    with torch.no_grad():
        splats = project_splats(gaussians, camera, (), near_plane=0.01)
    n, f32 = len(gaussians), np.float32
    records, boxes = np.zeros((n, SPLAT_RECORD), f32), np.zeros((n, 4), np.int32)
    view = tuple(f32(v) for v in world_to_camera(camera, torch.float32, torch.device("cpu"))[:3].reshape(-1).tolist())
    bounds = tuple(f32(b) for b in slope_bounds(camera.fx, camera.fy, camera.cx, camera.cy, 64, 48))
    array = lambda t: np.ascontiguousarray(t.numpy())  # noqa: E731
    project_numba(
        array(gaussians.means), array(gaussians.quats), array(gaussians.scales), array(gaussians.opacities), view,
        (f32(camera.fx), f32(camera.fy), f32(camera.cx), f32(camera.cy)), bounds, f32(0.01), 64, 48,
        records, boxes,
    )  # fmt: skip
    means2d, conics, depths = records[:, [U, V]], records[:, [CONIC_A, CONIC_B, CONIC_C]], records[:, DEPTH]
    drawn = boxes[:, 0] <= boxes[:, 1]
    # The same splats survive culling (the reference sorts them by depth, stably).
    order = np.flatnonzero(drawn)[np.argsort(depths[drawn], kind="stable")]
    assert 500 < len(order) < n and len(order) == len(splats.depths)
    assert np.array_equal(means2d[order], splats.means2d.numpy())
    assert np.array_equal(conics[order], splats.conics.numpy())
    assert np.array_equal(depths[order], splats.depths.numpy())
    # Both bin each splat into the same tiles.
    tiles = np.stack([boxes[order, 0] // 16, boxes[order, 1] // 16 + 1, boxes[order, 2] // 16, boxes[order, 3] // 16 + 1], 1)
    assert np.array_equal(tiles, splats.tile_ranges.numpy())
