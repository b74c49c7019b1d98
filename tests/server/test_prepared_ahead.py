"""Frames in flight begin their folds while the frames before them fold (`Session.prepare`), on a real
(in-process) uvicorn server: they are folded as prepared, and every prepared slot comes back."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from canonical_core.scene import PreparedFrame, Scene
from client.sdk import Client, frame_body
import server.session
from server.session import PREPARED_AHEAD

from .harness import in_process_server


def free_slots() -> int:
    taken = 0
    while PREPARED_AHEAD.acquire(blocking=False):
        taken += 1
    for _ in range(taken):
        PREPARED_AHEAD.release()
    return taken


def test_frames_in_flight_fold_as_prepared_and_give_their_slots_back(tmp_path, monkeypatch, frames):
    made = []
    fold = Scene.fold

    def recording(self, frame):
        made.append(isinstance(frame, PreparedFrame) and frame.evidence is not None)
        return fold(self, frame)

    monkeypatch.setattr(Scene, "fold", recording)
    slots = free_slots()
    labelled = [dict(f, labels=np.zeros(f["rgb"].shape[:2], np.int64), num_classes=2) for f in frames[:7]]
    with in_process_server(tmp_path / "data") as url, Client(url) as client:
        session = client.create_session(voxel_size=0.02)
        reports = list(session.add_frames(labelled[:6], in_flight=3))
        assert [r["frame_index"] for r in reports] == list(range(6))
        # refused in its fold, after its evidence was made: label channels unlike the earlier frames'
        # (sent past the SDK, which refuses it itself)
        odd = dict(frames[6], labels=np.zeros((*frames[6]["rgb"].shape[:2], 3), np.float32))
        r = httpx.post(f"{url}/v1/sessions/{session.id}/frames", content=frame_body(**odd),
                       headers={"Content-Type": "application/msgpack"})
        assert r.status_code == 422 and "labels" in r.text, r.text
        assert session.stats()["frames"] == 6
    assert made[0] is False  # the first frame chooses the settings left open: nothing is made before
    assert sum(made) >= 2  # frames posted behind it were prepared while it folded
    assert free_slots() == slots


@pytest.mark.parametrize("cap", ["PREPARED_MAX_BYTES", "PREPARED_MAX_PIXELS"])
def test_a_frame_over_the_caps_is_folded_without_being_prepared(tmp_path, monkeypatch, frames, cap):
    made = []
    fold = Scene.fold

    def recording(self, frame):
        made.append(isinstance(frame, PreparedFrame))
        return fold(self, frame)

    monkeypatch.setattr(Scene, "fold", recording)
    monkeypatch.setattr(server.session, cap, 1024)  # below any frame's evidence, and its pixels
    slots = free_slots()
    with in_process_server(tmp_path / "data") as url, Client(url) as client:
        session = client.create_session(voxel_size=0.02)
        assert len(list(session.add_frames(frames[:5], in_flight=3))) == 5
    assert made == [False] * 5
    assert free_slots() == slots
