import numpy as np
import pytest

from canonical_core import Camera
from canonical_core.resample import area_resize, depth_size_problem, resized_intrinsics


@pytest.mark.parametrize("factor, tolerance", [((2, 2), 0), ((4, 4), 0), ((2, 3), 1)])
def test_area_resize_by_whole_factors_is_the_rounded_block_mean(factor, tolerance):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    fx, fy = factor
    blocks = rgb.astype(np.int64).reshape(48 // fy, fy, 64 // fx, fx, 3).sum(axis=(1, 3))
    expected = (blocks + fx * fy // 2) // (fx * fy)  # the exact mean, rounded half up
    error = np.abs(area_resize(rgb, (64 // fx, 48 // fy)).astype(np.int64) - expected)
    assert error.max() <= tolerance  # exact for power-of-two blocks, else fixed point: within one level


def test_area_resize_by_other_factors_stays_an_area_average():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    out = area_resize(rgb, (40, 30))  # 1.6x: Pillow's box filter
    assert out.shape == (30, 40, 3) and out.dtype == np.uint8
    assert abs(float(out.mean()) - float(rgb.mean())) < 1.0  # the mean colour is kept
    flat = np.full((48, 64, 3), 77, np.uint8)
    assert np.array_equal(area_resize(flat, (40, 30)), np.full((30, 40, 3), 77, np.uint8))


def test_resized_intrinsics_is_the_cameras_own_rule_bit_for_bit():
    """The SDK resizes a frame's colour to its depth with this rule before it sends it, and the
    service's `Camera.resized` does the same with the whole image: the two cameras must be equal to
    the last bit, or the scenes differ."""
    K = np.array([[1439.7, 0, 959.3], [0, 1441.1, 721.9], [0, 0, 1]])
    camera = Camera(K, np.eye(4), 1920, 1440)
    for w, h in ((256, 192), (320, 240), (1919, 1439)):
        assert np.array_equal(resized_intrinsics(K, w / 1920, h / 1440), camera.resized(w, h).K64())
    half = resized_intrinsics(K, 0.5, 0.5)  # the image's edges stay its edges: c' + 0.5 = (c + 0.5) / 2
    assert half[0, 2] + 0.5 == pytest.approx((959.3 + 0.5) / 2) and half[0, 0] == pytest.approx(1439.7 / 2)
    assert np.array_equal(K, camera.K64())  # the input is not changed


@pytest.mark.parametrize("image, depth, problem", [
    ((1920, 1440), (256, 192), None),  # a phone's LiDAR: 7.5x on each side
    ((640, 480), (640, 480), None),  # the image's own size
    ((16, 12), (7, 5), None),  # rounded sizes within a pixel of the image's shape
    ((640, 480), (1280, 960), "is larger than the rgb image 640x480"),
    ((640, 480), (640, 360), "does not have the shape of the rgb image 640x480"),  # another camera's depth
    ((640, 480), (320, 480), "does not have the shape"),  # one side only
    ((640, 480), (320, 200), "does not have the shape"),
])
def test_depth_size_problem_names_depth_that_is_not_the_image_resampled(image, depth, problem):
    found = depth_size_problem(image, depth)
    if problem is None:
        assert found is None
    else:
        assert found.startswith(f"depth: {depth[0]}x{depth[1]}") and problem in found
