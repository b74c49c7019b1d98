"""A session's log restored from its frame archive, in process on real files: what the archive holds
was acknowledged, what it does not hold is left to the log's own rules, and a log of the old record
format is read by that format's rules."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import pytest

from canonical_core import SceneConfig
from canonical_core.datasets import synthetic_rgbd
from client.cli.capture import frame_arrays
from server import framelog, wire
from server.archive import ARCHIVE, SessionArchive
from server.durability import LOG, QUARANTINE, restore_session
from server.session_errors import Unrestorable
from server.store import SessionStore

from .harness import msgpack_frame

FRAMES = 6
OLD_FORMAT = Path(__file__).resolve().parents[1] / "fixtures" / "frames_v1.log"


@pytest.fixture(scope="module")
def payloads() -> list[bytes]:
    return [wire.pack(msgpack_frame(frame_arrays(f))) for f in synthetic_rgbd(num_frames=FRAMES, width=64, height=48)]


@pytest.fixture()
def session(tmp_path, payloads):
    """A session that folded `FRAMES` frames, every one archived; its files as a kill -9 leaves them."""
    store = SessionStore(tmp_path, max_sessions=4)
    store.open()
    session = store.create(SceneConfig(voxel_size=0.05))
    for payload in payloads:
        session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 10**6, 1e9)
    session.archive.flush()
    yield session
    session.archive.close()
    session.log.close()


def restored(session):
    restored, archive = restore_session(session.path, session.config, "all")
    restored.log.close()
    archive.close()
    return restored, archive


def records(session) -> list[framelog.Record]:
    return framelog.scan((session.path / LOG).read_bytes()).records


def damage(session, *offsets: int) -> bytes:
    data = bytearray((session.path / LOG).read_bytes())
    for offset in offsets:
        data[offset] ^= 0x10
    (session.path / LOG).write_bytes(bytes(data))
    return bytes(data)


def archive_lags(session, frames: int) -> None:
    """The archive's writer had archived the first ``frames`` frames when the service was killed."""
    archive = SessionArchive(session.path / ARCHIVE, "all")
    archive.cut(len(archive.entries) - frames)
    archive.close()


def test_a_damaged_record_is_restored_from_the_archive_and_the_records_after_it_from_the_log(session):
    archive_lags(session, 5)  # frame 5 is only in the log
    damage(session, records(session)[3].start + 100)  # frame 3's payload
    back, archive = restored(session)
    assert back.scene.frames == FRAMES and back.scene.digest() == session.scene.digest()
    assert [r.index for r in records(session)] == list(range(FRAMES)) and len(archive.entries) == FRAMES
    assert len(list((session.path / QUARANTINE).iterdir())) == 1


def test_damage_that_may_hold_a_frame_the_archive_lacks_is_reported_never_cut(session):
    archive_lags(session, 5)
    last = records(session)[-2:]
    damaged = damage(session, last[0].offset + 5, last[1].offset + 5)  # the length fields of frames 4 and 5
    with pytest.raises(Unrestorable, match="the damaged bytes hold more than the frames that archive.log holds"):
        restored(session)
    assert (session.path / LOG).read_bytes() == damaged
    assert [c.read_bytes() for c in (session.path / QUARANTINE).iterdir()] == [damaged]


def test_a_damaged_last_record_the_archive_lacks_is_reported(session):
    archive_lags(session, 5)
    damaged = damage(session, records(session)[-1].offset + 6)  # frame 5's length, longer by 64 KiB
    with pytest.raises(Unrestorable, match="damaged record"):
        restored(session)
    assert (session.path / LOG).read_bytes() == damaged


def format_1(record: framelog.Record) -> bytes:
    """``record`` as logs written before format 2 held it (`tests/fixtures/frames_v1.log`)."""
    magic = b"CGK1" if record.checkpoint else b"CGF1"
    crc = zlib.crc32(record.payload, zlib.crc32(struct.pack("<IQ", len(record.payload), record.index)))
    return framelog.FIELDS.pack(magic, len(record.payload), record.index, crc) + record.payload


def test_format_1_records_are_written_as_the_fixture_holds_them():
    data = OLD_FORMAT.read_bytes()
    assert b"".join(format_1(r) for r in framelog.scan(data).records) == data


@pytest.mark.parametrize("cut, frames", [("last 1000 bytes", FRAMES - 1), ("second-to-last midway", FRAMES - 1)])
def test_a_format_1_log_is_read_by_its_rules_and_goes_on_in_format_2(session, payloads, cut, frames):
    """Format 1 has no header CRC, and archives of its time could hold one frame never logged: its cut
    last record is a torn tail, and the archive's copy of it is cut. A second-to-last record cut midway
    is restored from the archive."""
    old = records(session)
    (session.path / LOG).write_bytes(b"".join(format_1(r) for r in old))
    size = {"last 1000 bytes": old[-1].end - 4 * len(old) - 1000,
            "second-to-last midway": old[-2].offset - 4 * (len(old) - 2) + 100}[cut]
    with open(session.path / LOG, "r+b") as f:
        f.truncate(size)
    back, archive = restored(session)
    assert back.scene.frames == frames and len(archive.entries) == frames
    restarted, archive = restore_session(session.path, session.config, "all")
    restarted.log.append(frames, payloads[frames - 1])
    restarted.log.close()
    archive.close()
    assert [r.version for r in records(session)][-2:] == [1 if cut == "last 1000 bytes" else 2, 2]


@pytest.mark.parametrize("lose", ["deleted", "truncated"])
def test_a_lost_snapshot_is_folded_again_from_the_archive_and_the_log(tmp_path, payloads, lose):
    """A snapshot gone or unreadable while the log goes on after it: the frames it held are in the
    archive, the later ones in the log (the last not archived yet), so the session is folded again from
    them, as it was, and the snapshot kept under quarantine/; a start no longer says they are lost."""
    store = SessionStore(tmp_path, max_sessions=4)
    store.open()
    session = store.create(SceneConfig(voxel_size=0.05))
    for k, payload in enumerate(payloads):
        session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 10**6, 1e9)
        if k == 3:
            session.snapshot()  # the log restarts at frame 4, after a checkpoint
    session.archive.flush()
    digest = session.scene.digest()
    session.archive.close()
    session.log.close()
    archive_lags(session, FRAMES - 1)  # frame 5 is only in the log
    snap = session.path / "scene.snap"
    held = snap.read_bytes()
    snap.unlink() if lose == "deleted" else snap.write_bytes(held[: len(held) // 2])
    back, archive = restored(session)
    assert back.scene.frames == FRAMES and back.scene.digest() == digest
    assert len(archive.entries) == FRAMES and snap.is_file()
    assert restored(session)[0].scene.digest() == digest  # and from the files it wrote
    kept = [p.read_bytes() for p in (session.path / QUARANTINE).glob("scene.snap.*")]
    assert kept == ([] if lose == "deleted" else [held[: len(held) // 2]])


def test_a_lost_snapshot_the_archive_cannot_make_whole_is_reported(tmp_path, payloads):
    """Retention "keyframes" keeps some frames only: the scene cannot be folded from them as it was."""
    store = SessionStore(tmp_path, max_sessions=4)
    store.open()
    session = store.create(SceneConfig(voxel_size=0.05), "keyframes")
    for k, payload in enumerate(payloads):
        session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 10**6, 1e9)
        if k == 3:
            session.snapshot()
    session.archive.close()
    session.log.close()
    (session.path / "scene.snap").unlink()
    with pytest.raises(Unrestorable, match="scene.snap is missing"):
        restore_session(session.path, session.config, "keyframes")
