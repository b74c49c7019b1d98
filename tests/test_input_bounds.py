"""Library-side bounds on absurd but finite inputs: each raises ValueError naming the field, at the edge."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, Scene, SceneConfig
from canonical_core.calibration import MAX_FOCAL_PER_SIDE, MAX_PRINCIPAL_OFFSET, MAX_TRANSLATION, MIN_FOCAL_PER_SIDE
from canonical_core.frame import (MAX_FEATURE_CHANNELS, MAX_LABEL_CHANNELS, MAX_RGB_ONLY_PIXELS, check_rgb_only,
                                  depth_warnings)

W, H = 64, 48


def K(fx=50.0, fy=50.0, cx=31.5, cy=23.5):
    return [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]


def pose(t=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, 3] = t
    return T


CAMERA_CASES = [
    ("fx 1e30", dict(K=K(fx=1e30)), "K", "fx=1e+30"),
    ("fy tiny", dict(K=K(fy=1e-9)), "K", "fy=1e-09"),
    ("fx above the bound", dict(K=K(fx=MAX_FOCAL_PER_SIDE * W * 1.01)), "K", "fx="),
    ("cx far outside", dict(K=K(cx=1e6)), "K", "principal point"),
    ("cy far below the image", dict(K=K(cy=-0.6 - MAX_PRINCIPAL_OFFSET * H)), "K", "principal point"),
    ("translation 1e12", dict(c2w=pose((0, 1e12, 0))), "c2w", "translation"),
    ("translation past the bound", dict(c2w=pose((MAX_TRANSLATION * 1.01, 0, 0))), "c2w", "translation"),
]


@pytest.mark.parametrize("change, field, message", [c[1:] for c in CAMERA_CASES], ids=[c[0] for c in CAMERA_CASES])
def test_absurd_cameras_are_refused(change, field, message):
    args = {"K": K(), "c2w": pose(), "width": W, "height": H, **change}
    with pytest.raises(ValueError) as info:
        Camera(**args)
    assert str(info.value).startswith(f"{field}: ") and message in str(info.value)


def test_camera_bounds_are_inclusive_edges():
    Camera(K(fx=MIN_FOCAL_PER_SIDE * W, fy=MAX_FOCAL_PER_SIDE * W, cx=-0.5, cy=H - 0.5), pose((MAX_TRANSLATION, 0, 0)), W, H)
    Camera(K(cx=W - 0.5 + MAX_PRINCIPAL_OFFSET * W, cy=-0.5 - MAX_PRINCIPAL_OFFSET * H), pose((-MAX_TRANSLATION, 0, 0)), W, H)


def test_a_frames_principal_point_lies_in_its_image():
    camera = Camera(K(cx=2 * W), pose(), W, H)  # a view may be a crop of a larger one
    with pytest.raises(ValueError, match=r"^K: principal point \(128, 23.5\) lies outside the image"):
        Frame(rgb=np.zeros((H, W, 3), np.uint8), camera=camera)
    Frame(rgb=np.zeros((H, W, 3), np.uint8), camera=Camera(K(cx=W - 0.5, cy=-0.5), pose(), W, H))


def _frame(w=W, h=H, **kwargs):
    return Frame(rgb=np.zeros((h, w, 3), np.uint8), camera=Camera(K(cx=(w - 1) / 2, cy=(h - 1) / 2), pose(), w, h), **kwargs)


@pytest.mark.parametrize("w, h", [(1, 1), (1, 48), (64, 7)])
def test_rgb_only_frames_too_small_to_sweep_are_refused(w, h):
    scene = Scene(SceneConfig(voxel_size=0.05))
    with pytest.raises(ValueError, match=rf"^rgb: a frame without depth of {w}x{h} pixels is too small"):
        scene.fold(_frame(w, h))
    assert scene.frames == 0
    assert scene.fold(_frame(w, h, depth=np.ones((h, w), np.float32))).observations == w * h  # with depth it folds


@pytest.mark.parametrize("name, limit", [("features", MAX_FEATURE_CHANNELS), ("labels", MAX_LABEL_CHANNELS)])
def test_channel_caps(name, limit):
    _frame(**{name: np.zeros((2, 2, limit), np.float32)})
    with pytest.raises(ValueError, match=rf"^{name}: {limit + 1} channels exceed the limit of {limit}"):
        _frame(**{name: np.zeros((2, 2, limit + 1), np.float32)})


def test_rgb_only_bound():
    check_rgb_only(_frame(), max_pixels=W * H)
    check_rgb_only(_frame(depth=np.ones((H, W), np.float32)), max_pixels=1)  # frames with depth are not bound by it
    with pytest.raises(ValueError, match=r"^rgb: a frame without depth of 64x48"):
        check_rgb_only(_frame(), max_pixels=W * H - 1)
    assert MAX_RGB_ONLY_PIXELS < 4096 * 4096


def test_scene_refuses_a_large_rgb_only_frame_unchanged():
    side = int(MAX_RGB_ONLY_PIXELS ** 0.5) + 1
    scene = Scene(SceneConfig(voxel_size=0.05))
    before = scene.digest()
    with pytest.raises(ValueError, match="^rgb: a frame without depth"):
        scene.fold(_frame(side, side))
    assert scene.frames == 0 and scene.digest() == before


@pytest.mark.parametrize("depth, message", [
    (np.zeros((H, W), np.float32), "no valid pixel"),
    (np.full((H, W), np.nan, np.float32), "no valid pixel"),
    (np.full((H, W), 1500.0, np.float32), "no pixel lies within the range 0.05 .. 20 m"),  # millimetres sent as metres
])
def test_depth_that_gives_nothing_is_reported(depth, message):
    scene = Scene(SceneConfig(voxel_size=0.05))
    report = scene.fold(_frame(depth=depth))
    assert report.observations == 0 and len(report.warnings) == 1
    assert report.warnings[0].startswith("depth: ") and message in report.warnings[0]
    assert report.to_dict()["warnings"] == report.warnings


def test_good_depth_has_no_warning():
    scene = Scene(SceneConfig(voxel_size=0.05))
    assert scene.fold(_frame(depth=np.ones((H, W), np.float32))).warnings == []
    assert depth_warnings(torch.ones(2, 2), 0.1, 10.0) == []


def test_scene_calls_name_the_bad_argument():
    with pytest.raises(ValueError, match="^config: expected a SceneConfig, got dict"):
        Scene({"voxel_size": 0.01})
    scene = Scene(SceneConfig(voxel_size=0.01))
    with pytest.raises(ValueError, match="^frame: expected a Frame, got str"):
        scene.fold("frame.png")
    for depth in (-1, 2.0, True):
        with pytest.raises(ValueError, match="^undo_depth: expected a non-negative integer"):
            scene.keep_undo(depth)
    with pytest.raises(ValueError, match="^min_support: expected >= 0"):
        scene.decode(min_support=-0.5)
    with pytest.raises(ValueError, match="^max_gaussians: expected a non-negative integer"):
        scene.decode(max_gaussians=-1)
    assert scene.frames == 0 and len(scene) == 0
