import math

import numpy as np
import pytest
import torch

from canonical_core import Camera
from canonical_core.calibration import OPENGL_TO_OPENCV, quaternion_to_matrix

K = [[500.0, 0, 320.0], [0, 480.0, 240.0], [0, 0, 1]]


def rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = np.r_[math.cos(angle / 2), math.sin(angle / 2) * axis]
    return quaternion_to_matrix(q)


def pose(R=np.eye(3), t=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def test_lift_project_round_trip_under_rotation():
    cam = Camera(K, pose(rotation([1, 2, 3], 0.7), [0.3, -0.2, 1.5]), 640, 480)
    uv = torch.tensor([[0.0, 0.0], [639.0, 479.0], [320.0, 240.0], [100.5, 400.25]])
    z = torch.tensor([0.5, 1.0, 2.0, 7.5])
    uv2, z2 = cam.project(cam.lift(uv, z))
    assert torch.allclose(uv2, uv, atol=1e-3) and torch.allclose(z2, z, atol=1e-5)


def test_principal_point_lifts_onto_optical_axis():
    cam = Camera(K, pose(t=[1, 2, 3]), 640, 480)
    x = cam.lift(torch.tensor([[320.0, 240.0]]), torch.tensor([2.0]))
    assert torch.allclose(x, torch.tensor([[1.0, 2.0, 5.0]]))


def test_opengl_and_w2c_constructors_agree():
    c2w = pose(rotation([0, 1, 0], 0.4), [1, 0, 0])
    cam = Camera(K, c2w, 640, 480)
    assert torch.allclose(Camera.from_w2c(K, np.linalg.inv(c2w), 640, 480).c2w, cam.c2w, atol=1e-6)
    assert torch.allclose(Camera.from_opengl(K, c2w @ OPENGL_TO_OPENCV, 640, 480).c2w, cam.c2w, atol=1e-6)


def test_from_tum_is_scalar_last():
    R = rotation([0, 0, 1], math.pi / 2)  # 90 degrees about z: q = (w, x, y, z) = (c, 0, 0, s)
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    cam = Camera.from_tum(K, [1, 2, 3, 0, 0, s, c], 640, 480)
    assert np.allclose(cam.c2w64()[:3, :3], R, atol=1e-9) and np.allclose(cam.c2w64()[:3, 3], [1, 2, 3])


def test_scaled_keeps_pixel_centres():
    cam = Camera(K, np.eye(4), 640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    # the ray through full-res pixel centre 1 (covering [0.5, 1.5]) passes half-res coordinate 0.25
    x = cam.lift(torch.tensor([[1.0, 1.0]]), torch.tensor([1.0]))
    uv, _ = half.project(x)
    assert torch.allclose(uv, torch.tensor([[0.25, 0.25]]), atol=1e-5)


@pytest.mark.parametrize("bad", [0, -0.5, float("nan"), "a", None, True])
def test_scaled_names_a_factor_that_is_no_positive_number(bad):
    with pytest.raises(ValueError, match="^factor: expected a positive number"):
        Camera(K, np.eye(4), 640, 480).scaled(bad)


def test_scaled_to_a_rounded_size_keeps_the_images_edges():
    """65 x 49 at 0.5 is 32 x 24 pixels: K follows that size, so the full image's far corner (the edge
    of pixel 64, 48) still projects to the edge of the small image's last pixel, not half a pixel past."""
    cam = Camera(K, np.eye(4), 65, 49)
    small = cam.scaled(0.5)
    assert (small.width, small.height) == (32, 24)
    corner = cam.lift(torch.tensor([[64.5, 48.5], [-0.5, -0.5]]), torch.tensor([1.0, 1.0]))
    uv, _ = small.project(corner)
    assert torch.allclose(uv, torch.tensor([[31.5, 23.5], [-0.5, -0.5]]), atol=1e-4)
    assert np.array_equal(small.K64(), cam.resized(32, 24).K64())


@pytest.mark.parametrize(
    "kwargs, field, message",
    [
        (dict(K=np.eye(2)), "K", "shape"),
        (dict(K=[[0, 0, 1], [0, 500, 1], [0, 0, 1]]), "K", "focal"),
        (dict(K=[[-5, 0, 1], [0, 500, 1], [0, 0, 1]]), "K", "focal"),
        (dict(K=[[500, 0, np.nan], [0, 500, 1], [0, 0, 1]]), "K", "NaN"),
        (dict(K=[[500, 3, 1], [0, 500, 1], [0, 0, 1]]), "K", "expected"),
        (dict(c2w=np.eye(3)), "c2w", "shape"),
        (dict(c2w=np.full((4, 4), np.nan)), "c2w", "NaN"),
        (dict(c2w=np.diag([1.0, 1.0, 1.1, 1.0])), "c2w", "orthonormal"),
        (dict(c2w=np.diag([1.0, 1.0, -1.0, 1.0])), "c2w", "determinant"),
        (dict(c2w=np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]])), "c2w", "bottom row"),
        (dict(width=0), "width", "positive"),
        (dict(height=2.5), "height", "positive"),
        (dict(K="abc"), "K", "numeric"),
    ],
)
def test_validation_names_field_and_problem(kwargs, field, message):
    args = dict(K=K, c2w=np.eye(4), width=640, height=480) | kwargs
    with pytest.raises(ValueError) as err:
        Camera(**args)
    assert str(err.value).startswith(field) and message in str(err.value)


def test_rotation_tolerance_is_1e_3():
    R = rotation([1, 0, 0], 0.3) * (1 + 4e-4)  # slightly off, within tolerance
    Camera(K, pose(R), 640, 480)
    with pytest.raises(ValueError, match="orthonormal"):
        Camera(K, pose(rotation([1, 0, 0], 0.3) * (1 + 2e-3)), 640, 480)


def test_accepts_3x4_and_torch_inputs():
    cam = Camera(torch.tensor(K), torch.eye(4)[:3], 640, 480)
    assert cam.c2w.shape == (4, 4) and cam.K.dtype == torch.float32


@pytest.mark.parametrize(
    "call, field, message",
    [
        (lambda cam: Camera.from_tum(K, [0, 0, 0, 0, 0, 1], 640, 480), "pose", "expected 7 values"),
        (lambda cam: Camera.from_tum(K, [0, 0, 0, 0, 0, 0, 0], 640, 480), "pose", "non-zero quaternion"),
        (lambda cam: Camera.from_tum(K, [0, 0, np.inf, 0, 0, 0, 1], 640, 480), "pose", "finite values"),
        (lambda cam: cam.scaled(0), "factor", "positive"),
        (lambda cam: cam.lift(torch.zeros(4, 3), torch.ones(4)), "uv", "[N, 2]"),
        (lambda cam: cam.lift(torch.zeros(4, 2), torch.ones(3)), "depth", "[4]"),
        (lambda cam: cam.project(torch.zeros(4, 2)), "points", "[N, 3]"),
    ],
)
def test_constructors_and_geometry_name_the_bad_argument(call, field, message):
    with pytest.raises(ValueError) as err:
        call(Camera(K, np.eye(4), 640, 480))
    assert str(err.value).startswith(field) and message in str(err.value)
