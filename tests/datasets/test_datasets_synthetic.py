"""The generated sample: shapes, exact depth (analytic checks), determinism, texture."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core.datasets import FrameSequence, synthetic_rgbd
from canonical_core.datasets.synthetic import cast_rays, look_at, make_scene


@pytest.fixture(scope="module")
def sample():
    return synthetic_rgbd(num_frames=12, width=160, height=120, seed=0)


def _lift64(frame) -> tuple[np.ndarray, np.ndarray]:  # world points [N, 3], pixel indices [N, 2]
    depth = frame.depth.numpy().astype(np.float64)
    v, u = np.nonzero(depth > 0)
    K, c2w = frame.camera.K64(), frame.camera.c2w64()
    z = depth[v, u]
    pc = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    return pc @ c2w[:3, :3].T + c2w[:3, 3], np.stack([u, v], -1)


def test_shapes_and_camera(sample):
    assert isinstance(sample, FrameSequence) and len(sample) == 12
    assert sample.frame_ids[:2] == ["000000", "000001"]
    f = sample[3]
    assert f.rgb.shape == (120, 160, 3) and f.rgb.dtype == torch.uint8
    assert f.depth.shape == (120, 160) and f.depth.dtype == torch.float32
    assert f.camera.fx == f.camera.fy == 128.0 and (f.camera.cx, f.camera.cy) == (79.5, 59.5)
    valid = f.depth[f.depth > 0]
    assert 0.2 < (f.depth == 0).float().mean() < 0.5  # sky above the ground's far edge
    assert 0.3 < float(valid.min()) and float(valid.max()) < 4.0


def test_default_size():
    f = synthetic_rgbd()[0]
    assert (f.width, f.height) == (320, 240) and len(synthetic_rgbd()) == 24


def test_lifted_depth_lies_on_the_scene_surfaces(sample):
    scene = make_scene(0)
    points, _ = _lift64(sample[5])
    on_ground = (np.abs(points[:, 2]) < 1e-5) & (np.abs(points[:, :2]) <= scene.ground_half_size + 1e-5).all(-1)
    lo, hi = scene.boxes[:, 0], scene.boxes[:, 1]
    inside = ((points[:, None] >= lo - 1e-5) & (points[:, None] <= hi + 1e-5)).all(-1)  # [N, B]
    on_face = (np.minimum(np.abs(points[:, None] - lo), np.abs(points[:, None] - hi)) < 1e-5).any(-1)
    on_box = (inside & on_face).any(-1)
    assert (on_ground | on_box).all()
    assert on_ground.sum() > 1000 and on_box.sum() > 500


def test_depth_agrees_across_views_exactly(sample):
    # lift frame 0's pixels, cast frame 3's ray through each exact (sub-pixel) projection: the first
    # hit is the lifted point itself, or something in front of it (occlusion), never behind it
    a, b = sample[0], sample[3]  # about 33 degrees apart on the arc
    points, uv = _lift64(a)
    c2w = b.camera.c2w64()
    to_point = points - c2w[:3, 3]
    z = to_point @ c2w[:3, 2]
    rays = to_point / z[:, None]  # camera z = 1: ray parameter = z-depth
    t, rgb = cast_rays(make_scene(0), np.broadcast_to(c2w[:3, 3], rays.shape), rays)
    assert (t <= z + 1e-6).all()
    visible = np.abs(t - z) < 1e-6
    assert visible.mean() > 0.8
    # Lambertian shading: the same point has the same colour from both views
    same = (rgb[visible] == a.rgb.numpy()[uv[visible, 1], uv[visible, 0]]).all(-1)
    assert same.mean() > 0.99


def test_deterministic_per_seed():
    a, b, c = (synthetic_rgbd(num_frames=3, width=64, height=48, seed=s)[2] for s in (4, 4, 5))
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
    assert not torch.equal(a.rgb, c.rgb) and not torch.equal(a.depth, c.depth)


def test_textures_are_varied(sample):
    rgb = sample[0].rgb.reshape(-1, 3).numpy()
    assert len(np.unique(rgb, axis=0)) > 1000
    patterns = make_scene(0).patterns
    assert set(patterns[1:].tolist()) == {0, 1, 2}  # checker, stripes and noise boxes


def test_look_at_convention():
    T = look_at((2.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert np.allclose(T[:3, 2], [-1, 0, 0])  # z forward
    assert np.allclose(T[:3, 1], [0, 0, -1])  # y down (world z is up)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    with pytest.raises(ValueError, match="parallel"):
        look_at((0, 0, 2), (0, 0, 0))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"num_frames": 0}, "num_frames: expected an integer >= 1, got 0"),
        ({"width": 4}, "width: expected an integer >= 8, got 4"),
        ({"height": 10.0}, "height: expected an integer >= 8, got 10.0"),
        ({"seed": "a"}, "seed: expected an integer, got 'a'"),
    ],
)
def test_input_checks(kwargs, message):
    with pytest.raises(ValueError, match=message):
        synthetic_rgbd(**kwargs)
