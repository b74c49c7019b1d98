"""The SDK's argument errors: raised before anything is sent, each naming the argument and the problem."""

from __future__ import annotations

import numpy as np
import pytest

from client.cli.launch import free_port
from client.sdk import Client, Session, frame_body

RGB = np.zeros((4, 4, 3), np.uint8)
K = np.array([[4.0, 0, 2], [0, 4, 2], [0, 0, 1]])


@pytest.fixture
def session():
    with Client(f"http://127.0.0.1:{free_port()}") as client:  # nothing listens: a request would fail otherwise
        yield Session(client, "s")


@pytest.mark.parametrize("call, message", [
    (lambda s: s.add_frame(RGB, np.eye(4), np.eye(4), downscale=False), r"^K: expected a 3x3 matrix, got shape \[4, 4\]$"),
    (lambda s: s.add_frame(RGB, K, np.eye(3), downscale=False), r"^c2w: expected a 4x4 matrix, got shape \[3, 3\]$"),
    (lambda s: s.add_frame(RGB, "fx fy", np.eye(4), downscale=False), r"^K: expected a 3x3 matrix of numbers"),
    (lambda s: s.render(np.eye(4), np.eye(4), 4, 4), r"^K: expected a 3x3 matrix"),
    (lambda s: s.render(K, np.eye(3), 4, 4), r"^c2w: expected a 4x4 matrix"),
    (lambda s: s.update_poses({"frame-7": np.eye(3)}), r"^poses\.frame-7: expected a 4x4 matrix, got shape \[3, 3\]$"),
    # one key as a string: sent as its characters it would remove frames 3 and 4
    (lambda s: s.update_poses({}, remove="34"), r"^remove: expected a list of frame keys, got the str '34'$"),
], ids=["frame K", "frame c2w", "K not numbers", "render K", "render c2w", "a pose", "remove one string"])
def test_matrix_errors_name_the_argument(session, call, message):
    with pytest.raises(ValueError, match=message):
        call(session)


@pytest.mark.parametrize("kwargs, message", [
    ({"rgb": np.zeros((4, 4, 3), np.int64)}, r"^rgb: dtype int64 cannot travel"),
    ({"rgb": "frame-000000.color.png"}, r"^rgb: expected an array or the image file's bytes, got the path"),
    ({"depth": "frame-000000.depth.png"}, r"^depth: expected an array or the image file's bytes, got the path"),
], ids=["rgb dtype", "rgb a path", "depth a path"])
def test_frame_arrays_the_wire_cannot_carry_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        frame_body(**{"rgb": RGB, "K": K, "c2w": np.eye(4), **kwargs})


def test_frame_body_names_the_matrix_too():
    with pytest.raises(ValueError, match=r"^K: expected a 3x3 matrix, got shape \[2\]$"):
        frame_body(RGB, [1.0, 2.0], np.eye(4))


@pytest.mark.parametrize("settings, message", [
    ({"voxel_size": float("nan")}, "^voxel_size: expected a finite number, got nan$"),
    ({"voxel_size": 0.01, "range": {"near": float("inf")}}, "^range.near: expected a finite number, got inf$"),
], ids=["voxel size", "a group's setting"])
def test_settings_json_cannot_carry_are_refused_naming_them(settings, message):
    with Client(f"http://127.0.0.1:{free_port()}") as client:
        with pytest.raises(ValueError, match=message):
            client.create_session(**settings)
