"""The camera track (what the viewer draws and snaps to): one row per frame the session holds, with
its current pose, through appends, a torn append, frames sent again, pose corrections, removals
and kill -9, on files and on a real service."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from canonical_core import Camera
from client.sdk import Client
from server.schemas import InputCamerasOut
from server.track import CAMERAS_FILE, ROW_BYTES, append_camera, correct_track, read_track

from .harness import VOXEL, ServerProcess, wait_for

K = [[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]]


def pose(x: float) -> np.ndarray:  # [4, 4]
    c2w = np.eye(4)
    c2w[0, 3] = x
    return c2w


def test_appends_skip_a_frame_the_track_holds_and_cut_a_torn_row_before_the_next(tmp_path):
    for k in range(3):
        append_camera(tmp_path, k, Camera(K, pose(k), 640, 480))
    append_camera(tmp_path, 1, Camera(K, pose(9), 640, 480))  # frame 1 sent again: its row stays as it was
    path = tmp_path / CAMERAS_FILE
    with open(path, "ab") as f:
        f.write(b"\0" * 40)  # a crash mid-append
    append_camera(tmp_path, 3, Camera(K, pose(3), 640, 480))
    assert path.stat().st_size == 4 * ROW_BYTES
    track = read_track(path, frames=4)
    assert track[:, 0].tolist() == [0, 1, 2, 3] and track[:, 10].tolist() == [0.0, 1.0, 2.0, 3.0]  # x of each c2w


def test_a_correction_rewrites_poses_drops_removed_frames_and_renumbers_the_rest(tmp_path):
    for k in range(6):
        append_camera(tmp_path, k, Camera(K, pose(k), 640, 480))
    correct_track(tmp_path, {2: pose(20.0), 5: pose(50.0)}, removed={1, 3})
    track = read_track(tmp_path / CAMERAS_FILE, frames=10)
    assert track[:, 0].tolist() == [0, 1, 2, 3]  # frames 0, 2, 4, 5 as the scene numbers them now
    assert track[:, 10].tolist() == [0.0, 20.0, 4.0, 50.0]
    assert track[:, 1:3].tolist() == [[640, 480]] * 4 and not (tmp_path / "cameras.tmp").exists()


@pytest.mark.slow
@pytest.mark.realdata
def test_the_service_track_follows_corrections_removals_and_kill9(tmp_path, frames):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_frames=3, snapshot_every_seconds=3600,
                         warm_up="false")
    few = frames[:6]
    try:
        client = Client(proc.start().url)
        session = client.create_session(voxel_size=VOXEL)
        for kwargs in few:
            session.add_frame(**kwargs)

        def track() -> list[dict]:
            answer = httpx.get(f"{proc.url}/v1/sessions/{session.id}/cameras").json()
            assert answer["frames"] == len(answer["cameras"])
            return answer["cameras"]

        moved = few[2]["c2w"] @ pose(0.05)
        session.update_poses({few[2]["frame_id"]: moved}, remove=[few[4]["frame_id"]])
        cameras = track()
        assert [c["frame_index"] for c in cameras] == [0, 1, 2, 3, 4]
        assert np.allclose(np.reshape(cameras[2]["c2w"], (4, 4)), moved)
        assert np.allclose(np.reshape(cameras[4]["c2w"], (4, 4)), few[5]["c2w"])  # frame 5 is the fifth now
        session.add_frame(**{**few[4], "frame_id": "again"})  # the removed frame, sent again under a new id
        cameras = track()
        assert [c["frame_index"] for c in cameras] == list(range(6))
        assert np.allclose(np.reshape(cameras[5]["c2w"], (4, 4)), few[4]["c2w"])
        url = f"{proc.url}/v1/sessions/{session.id}/cameras"
        newer = InputCamerasOut.model_validate(httpx.get(url, params={"since": 4}).json())  # the documented shape
        assert newer.frames == 6 and [c.model_dump() for c in newer.cameras] == cameras[4:]
        assert httpx.get(url, params={"since": 6}).json()["cameras"] == []
        refused = httpx.get(url, params={"since": -1})
        assert refused.status_code == 422 and "since" in refused.text

        proc.kill9()
        session = Client(proc.start().url).session(session.id)
        session.add_frame(**{**few[4], "frame_id": "again"})  # a retry after the restart: the same frame
        assert track() == cameras

        # a correction re-folded in the background changes the track when its scene is swapped in
        status = session.update_poses({few[0]["frame_id"]: moved}, remove=[few[1]["frame_id"]], wait=False)
        assert status["state"] == "pending"
        assert wait_for(lambda: session.correction(status["correction_id"])["state"] == "done", 120)
        after = track()
        assert [c["frame_index"] for c in after] == list(range(5))
        assert np.allclose(np.reshape(after[0]["c2w"], (4, 4)), moved) and after[1:] == [
            {**c, "frame_index": c["frame_index"] - 1} for c in cameras[2:]]
    finally:
        proc.kill9()
