"""Compact frames on a real service: the frame log and the archive keep the bytes the client sent
(PNG colour, zstandard depth), and a session restored from them, after kill -9 or a graceful stop,
has the digest of the same frames sent as raw arrays."""

from __future__ import annotations

import msgpack
import pytest

from client.sdk import Client, frame_body
from server import framelog
from server.archive import ARCHIVE
from server.payloads import decompress_payload
from server.wire import unpack

from .harness import VOXEL, ServerProcess, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


def archived_payloads(path) -> list[bytes]:
    """The wire payloads of an archive's frame records, read from its file as it is."""
    out = []
    for record in framelog.scan(path.read_bytes()).records:
        body = msgpack.unpackb(record.payload, strict_map_key=False)
        if "arrival" in body:
            out.append(decompress_payload(body["message"]))
    return out


def test_log_and_archive_keep_the_clients_bytes_and_restore_to_the_same_scene(tmp_path, frames):
    frames = frames[:6]
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_frames=1000,
                         snapshot_every_seconds=3600)
    proc.start()
    try:
        with Client(proc.url) as client:
            raw = client.create_session(voxel_size=VOXEL)
            for kwargs in frames:
                raw.add_frame(**kwargs, codec="raw")
            expected = raw.digest()["sha256"]
            session = client.create_session(voxel_size=VOXEL)
            assert len(list(session.add_frames(frames, in_flight=3))) == len(frames)
            assert session.digest()["sha256"] == expected  # compact and raw frames fold alike
            assert wait_for(lambda: session.stats()["archive_frames"] == len(frames))
        proc.kill9()

        sent = [frame_body(**kwargs) for kwargs in frames]  # the SDK's default: compact, deterministic
        msg = unpack(sent[0])
        assert msg["rgb"][:8] == b"\x89PNG\r\n\x1a\n" and msg["depth"]["codec"] == "zstd"
        assert sum(map(len, sent)) < sum(map(len, (frame_body(**k, codec="raw") for k in frames))) / 2
        folder = tmp_path / "data" / "sessions" / session.id
        logged = [r.payload for r in framelog.scan((folder / "frames.log").read_bytes()).records if not r.checkpoint]
        assert logged == sent and archived_payloads(folder / ARCHIVE) == sent

        proc.start()  # after kill -9: the snapshot-less log is folded again
        with Client(proc.url) as client:
            assert client.session(session.id).digest()["sha256"] == expected
        proc.stop()  # graceful: a snapshot, and the log restarted
        proc.start()
        with Client(proc.url) as client:
            restored = client.session(session.id)
            assert restored.digest()["sha256"] == expected
            # a correction re-folds the archive's frames: the same scene as from raw arrays
            last = frames[-1]["frame_id"]
            for target in (restored, client.session(raw.id)):
                assert target.remove_frame(last)["frames"] == len(frames) - 1
            assert restored.digest()["sha256"] == client.session(raw.id).digest()["sha256"]
    finally:
        proc.stop()
