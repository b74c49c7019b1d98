"""Crash safety: kill -9 after acknowledgements (and mid-request), restart on the same data directory,
and compare with an uninterrupted run; torn log tails are dropped cleanly."""

from __future__ import annotations

import threading
import time

import pytest

from client.sdk import Client
from server import framelog

from .harness import VOXEL, ServerProcess, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


def test_kill9_restart_keeps_every_acknowledged_frame(tmp_path, frames, reference):
    data = tmp_path / "data"
    # snapshot every 4 frames: restarts load a snapshot *and* replay a log tail
    proc = ServerProcess(data, tmp_path / "server.log", snapshot_every_frames=4, snapshot_every_seconds=3600)

    def restart() -> Client:
        proc.start()
        return Client(proc.url)

    def check(client: Client, session_id: str, frames_expected: int | None = None) -> int:
        digest = client.session(session_id).digest()
        if frames_expected is not None:
            assert digest["frames"] == frames_expected
        assert digest["sha256"] == reference[digest["frames"]]["sha256"], f"state differs after {digest['frames']} frames"
        return digest["frames"]

    try:
        client = restart()
        session = client.create_session(voxel_size=VOXEL)
        sid, log_path = session.id, data / "sessions" / session.id / "frames.log"
        for kwargs in frames[:3]:  # acknowledged, log only (no snapshot yet)
            session.add_frame(**kwargs)
        proc.kill9()

        client = restart()
        check(client, sid, 3)
        session = client.session(sid)
        for kwargs in frames[3:7]:  # a snapshot at 4 frames, then 5..7 in the log
            session.add_frame(**kwargs)
        assert wait_for(lambda: session.stats()["snapshot_frames"] == 4)  # written off the acknowledged path
        assert wait_for(lambda: session.stats()["archive_frames"] == 7)  # archived off the acknowledged path
        proc.kill9()
        assert (data / "sessions" / sid / "scene.snap").exists()

        # the last acknowledged record cut short (as a crash mid-append would leave it): the archive,
        # which holds the frame, tells it from a torn tail, and restores it on start
        size = log_path.stat().st_size
        with open(log_path, "r+b") as f:
            f.truncate(size - 5)
        client = restart()
        check(client, sid, 7)
        assert log_path.stat().st_size == size  # the record as it was

        # kill -9 while frames are in flight: every acknowledged one survives, the state is a prefix
        session, acked, stop = client.session(sid), [], threading.Event()

        def stream():
            for kwargs in frames[7:]:
                if stop.is_set():
                    return
                try:
                    acked.append(session.add_frame(**kwargs)["frame_index"])
                except Exception:
                    return

        sender = threading.Thread(target=stream)
        sender.start()
        while len(acked) < 2 and sender.is_alive():
            time.sleep(0.002)
        stop.set()
        proc.kill9()
        sender.join()
        with open(log_path, "ab") as f:  # and a torn header after the last record
            f.write(b"CGF2\x10\x00")
        client = restart()
        frames_now = check(client, sid)
        assert frames_now >= 7 + len(acked)
        session = client.session(sid)
        for kwargs in frames[frames_now:]:
            session.add_frame(**kwargs)
        check(client, sid, len(frames))

        # a graceful stop snapshots everything and restarts the log with a checkpoint of the snapshot's frames
        proc.stop()
        records = framelog.scan(log_path.read_bytes()).records
        assert [(r.checkpoint, r.index) for r in records] == [(True, len(frames))]
        assert (data / "sessions" / sid / "scene.snap").exists()
    except BaseException:
        print(proc.log())
        raise
    finally:
        proc.kill9()
