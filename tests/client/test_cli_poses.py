"""``canonical poses``: pose files in the loaders' formats, sent as one correction to a real service."""

from __future__ import annotations

import json

import numpy as np
import pytest

from canonical_core.calibration import quaternion_to_matrix
from canonical_core.datasets import load_deep_video_mvs, load_tum
from client import cli
from client.cli.poses import read_pose_file
from client.sdk import Client
from tests.datasets.conftest import hololens_path, slambook_path  # noqa: F401 (fixtures)
from tests.server.test_poses_api import drifted


def matrix_to_tum(T: np.ndarray) -> list[float]:
    """4x4 c2w -> tx ty tz qx qy qz qw (scalar last), the inverse of the TUM reader."""
    R = T[:3, :3]
    w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
    x, y, z = (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)
    return [*T[:3, 3], x, y, z, w]


@pytest.mark.realdata
def test_pose_files_read_as_the_loaders_read_them(slambook_path, hololens_path):
    seq = load_tum(slambook_path, K=(518.0, 519.0, 325.5, 253.5))
    poses = read_pose_file(slambook_path / "pose.txt")  # 7 columns: line k = frame k (its arrival index)
    assert list(poses) == list(range(len(seq)))
    for k, frame in enumerate(seq):
        np.testing.assert_allclose(poses[k], frame.camera.c2w64(), atol=1e-6)
    walk = load_deep_video_mvs(hololens_path, max_frames=3)
    poses = read_pose_file(hololens_path / "poses.txt")  # 16 numbers a line
    for k, frame in enumerate(walk):
        np.testing.assert_allclose(poses[k], frame.camera.c2w64(), atol=1e-6)


def test_keyed_lines_and_errors_name_the_line(tmp_path):
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix([np.cos(0.2), 0, np.sin(0.2), 0])
    T[:3, 3] = [0.1, -0.2, 0.3]
    path = tmp_path / "poses.txt"
    path.write_text("# key tx ty tz qx qy qz qw\n" + "a " + " ".join(map(str, matrix_to_tum(T))) + "\n\n"
                    + "b " + " ".join(map(str, T.reshape(16))) + "\n")
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())  # a Windows editor's byte-order mark: not part of the key
    poses = read_pose_file(path)
    assert list(poses) == ["a", "b"]
    np.testing.assert_allclose(poses["a"], T, atol=1e-9)
    np.testing.assert_allclose(poses["b"], T, atol=1e-12)
    for text, problem in (("1 2 3\n", "expected 7 .* got 3$"), ("0 0 0 0 0 0 x\n", "could not convert"),
                          ("frame-7 0 0 0 0 0 1\n", "expected 7 .* got 6 after the key 'frame-7'"),
                          ("a 0 0 0 0 0 0 1\na 0 0 0 0 0 0 1\n", "earlier line"),
                          (" ".join(["2"] * 16) + "\n", "bottom row")):
        path.write_text(text)
        with pytest.raises(ValueError, match=rf"^{path}:\d+: .*{problem}"):
            read_pose_file(path)


@pytest.mark.realdata
def test_canonical_poses_corrects_a_drifted_session(server, frames, tmp_path, capsys):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=0.008)
        for kwargs in drifted(frames):
            session.add_frame(**kwargs)
        clean = client.create_session(voxel_size=0.008)
        for kwargs in frames[1:]:
            clean.add_frame(**kwargs)
        path = tmp_path / "true.txt"  # 4x4 per line, no keys: line k is the frame of arrival index k
        path.write_text("".join(" ".join(map(repr, kw["c2w"].reshape(16).tolist())) + "\n" for kw in frames))
        assert cli.main(["poses", str(path), "--session", session.id, "--url", server.url,
                         "--remove", frames[0]["frame_id"], "--json"]) == 0
        out, err = capsys.readouterr()
        assert f"{len(frames) - 1} poses corrected, 1 frames removed" in err  # not the removed one
        assert json.loads(out) == {**json.loads(out), "corrected": len(frames) - 1, "removed": 1, "state": "done"}
        assert session.digest()["sha256"] == clean.digest()["sha256"]
        assert cli.main(["poses", "--session", session.id, "--url", server.url]) == 2
        path.write_text("nope " + " ".join(map(repr, np.eye(4).reshape(16).tolist())) + "\n")
        assert cli.main(["poses", str(path), "--session", session.id, "--url", server.url]) == 1
        assert "poses.nope" in capsys.readouterr().err
        assert session.digest()["sha256"] == clean.digest()["sha256"]


@pytest.mark.realdata
def test_lines_without_keys_name_arrivals_even_where_frame_ids_are_numbers(server, frames, tmp_path, capsys):
    """A capture whose frame ids are numbers (slambook's are its lines counted from 1): line k of a
    pose file without keys is still frame k, not the frame whose id is "k"; a line the session has
    no frame for is named by the file's line."""
    numbered = [{**kw, "frame_id": str(k + 1)} for k, kw in enumerate(frames[:4])]
    with Client(server.url) as client:
        session = client.create_session(voxel_size=0.008)
        for kwargs in drifted(numbered):
            session.add_frame(**kwargs)
        clean = client.create_session(voxel_size=0.008)
        for kwargs in numbered:
            clean.add_frame(**kwargs)
        path = tmp_path / "true.txt"
        path.write_text("".join(" ".join(map(repr, kw["c2w"].reshape(16).tolist())) + "\n" for kw in numbered))
        assert cli.main(["poses", str(path), "--session", session.id, "--url", server.url]) == 0, capsys.readouterr().err
        assert session.digest()["sha256"] == clean.digest()["sha256"]
        with path.open("a") as f:  # a fifth pose for a session of four frames
            f.write(" ".join(["0", "0", "0", "0", "0", "0", "1"]) + "\n")
        assert cli.main(["poses", str(path), "--session", session.id, "--url", server.url]) == 1
        assert f"{path}:5: poses.4: no kept frame" in capsys.readouterr().err
        assert session.digest()["sha256"] == clean.digest()["sha256"]
