"""Damage to acknowledged log records after a kill -9, on a real service process and real files: told
apart from a torn tail (a crash mid-append), restored from the frame archive where it holds the frame,
reported where nothing can restore it, and never answered with fewer frames than were acknowledged."""

from __future__ import annotations

import contextlib
import shutil

import httpx
import pytest

from client.sdk import Client
from server import framelog
from server.durability import LOG, QUARANTINE

from .harness import VOXEL, ServerProcess, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]
ACKNOWLEDGED = 10


def server(tmp_path, data) -> ServerProcess:
    return ServerProcess(data, tmp_path / "server.log", snapshot_every_seconds=3600, snapshot_every_frames=1000,
                         warm_up="false")


def archived_frames(folder) -> int:
    """The frame records in a session's archive file (read by this process, while the service writes it)."""
    path = folder / "archive.log"
    return len(framelog.scan(path.read_bytes()).records) if path.is_file() else 0


@pytest.fixture(scope="module")
def killed(tmp_path_factory, frames) -> dict:
    """Session folders (retention -> folder) of a service killed with kill -9 once each had
    `ACKNOWLEDGED` frames acknowledged and (all, keyframes) archived by the archive's writer."""
    root = tmp_path_factory.mktemp("killed")
    proc = server(root, root / "data").start()
    try:
        folders = {}
        for retention in ("all", "keyframes", "none"):
            session = Client(proc.url).create_session(voxel_size=VOXEL, archive_retention=retention)
            for kwargs in frames[:ACKNOWLEDGED]:
                session.add_frame(**kwargs)
            folders[retention] = root / "data" / "sessions" / session.id
            if retention != "none":
                assert wait_for(lambda: archived_frames(folders[retention]) == ACKNOWLEDGED)
        proc.kill9()
        return folders
    except BaseException:
        print(proc.log())
        raise
    finally:
        proc.kill9()


def copy_of(killed: dict, retention: str, tmp_path):
    """A data directory holding a copy of the killed service's session of ``retention``: (data, id, its log)."""
    data = tmp_path / "data"
    target = data / "sessions" / killed[retention].name
    shutil.copytree(killed[retention], target)
    return data, target.name, target / LOG


def records_of(log) -> list[framelog.Record]:
    return [r for r in framelog.scan(log.read_bytes()).records if not r.checkpoint]


def flip_length_bit_of_last_record(log) -> None:
    data = bytearray(log.read_bytes())
    data[records_of(log)[-1].offset + 6] ^= 0x01  # the length's third byte: 64 KiB longer, past the end
    log.write_bytes(bytes(data))


def cut_to(log, size: int) -> None:
    with open(log, "r+b") as f:
        f.truncate(size)


def cut_last_1000_bytes(log) -> None:
    cut_to(log, log.stat().st_size - 1000)


def cut_second_to_last_record_midway(log) -> None:
    record = records_of(log)[-2]
    cut_to(log, record.offset + (record.end - record.offset) // 2)


@contextlib.contextmanager
def restarted(killed: dict, retention: str, tmp_path, damage):
    """The killed service's session of ``retention``, its log damaged by ``damage``, served by a new
    service: yields (the service, the session's id, its log, the log's bytes as damaged)."""
    data, sid, log = copy_of(killed, retention, tmp_path)
    damage(log)
    damaged = log.read_bytes()
    proc = server(tmp_path, data).start()
    try:
        yield proc, sid, log, damaged
    except BaseException:
        print(proc.log())
        raise
    finally:
        proc.kill9()


def assert_restored_from_the_archive(proc, sid, log, damaged: bytes, reference) -> None:
    """Every acknowledged frame served, the state of the uninterrupted run, the archive whole, the
    damaged log kept under quarantine/ and the restore logged."""
    stats = Client(proc.url).session(sid).stats()
    assert stats["frames"] == ACKNOWLEDGED and stats["state"] == "ok" and stats["problem"] is None
    assert stats["archive_frames"] == ACKNOWLEDGED and stats["archive_problem"] is None
    assert Client(proc.url).session(sid).digest()["sha256"] == reference[ACKNOWLEDGED]["sha256"]
    assert [r.index for r in records_of(log)] == list(range(ACKNOWLEDGED))
    assert [c.read_bytes() for c in (log.parent / QUARANTINE).iterdir()] == [damaged]
    assert "restored from archive.log" in proc.log()


def test_a_flipped_bit_in_the_last_records_length_is_damage_restored_from_the_archive(killed, tmp_path, reference):
    with restarted(killed, "all", tmp_path, flip_length_bit_of_last_record) as (proc, sid, log, damaged):
        assert_restored_from_the_archive(proc, sid, log, damaged, reference)


def test_a_flipped_bit_in_the_last_records_length_without_an_archive_is_reported(killed, tmp_path):
    with restarted(killed, "none", tmp_path, flip_length_bit_of_last_record) as (proc, sid, log, damaged):
        r = httpx.get(f"{proc.url}/v1/sessions/{sid}")
        assert r.status_code == 409 and "damaged record" in r.json()["error"]["message"]
        listed = {s["id"]: s for s in httpx.get(f"{proc.url}/v1/sessions").json()["sessions"]}
        assert listed[sid]["state"] == "unavailable"
        assert log.read_bytes() == damaged  # never cut


def test_the_last_1000_bytes_cut_after_acknowledgement_are_restored_from_the_archive(killed, tmp_path, reference):
    with restarted(killed, "all", tmp_path, cut_last_1000_bytes) as (proc, sid, log, damaged):
        assert_restored_from_the_archive(proc, sid, log, damaged, reference)


def test_a_second_to_last_record_cut_midway_is_restored_from_the_archive(killed, tmp_path, reference):
    with restarted(killed, "all", tmp_path, cut_second_to_last_record_midway) as (proc, sid, log, damaged):
        assert_restored_from_the_archive(proc, sid, log, damaged, reference)


def test_a_cut_the_archive_cannot_restore_is_reported_until_a_repair(killed, tmp_path, reference):
    """Retention "keyframes" holds the last frame's record but not its content: the session is not
    served with fewer frames than were acknowledged; a repair that drops the frame makes it so."""
    from server.store import SessionStore

    with restarted(killed, "keyframes", tmp_path, cut_last_1000_bytes) as (proc, sid, log, _):
        r = httpx.get(f"{proc.url}/v1/sessions/{sid}")
        assert r.status_code == 409 and r.json()["error"]["code"] == "session_unavailable"
        problem = r.json()["error"]["message"]
        assert f"frame {ACKNOWLEDGED - 1} was acknowledged" in problem and "canonical repair" in problem
    store = SessionStore(log.parents[2], max_sessions=8)
    try:
        assert f"now holds {ACKNOWLEDGED - 1} frames" in store.repair(sid, "truncate")
    finally:
        store.close()
    proc = server(tmp_path, log.parents[2]).start()
    try:
        stats = Client(proc.url).session(sid).stats()
        assert stats["frames"] == ACKNOWLEDGED - 1 and stats["state"] == "ok" and stats["archive_problem"] is None
        assert Client(proc.url).session(sid).digest()["sha256"] == reference[ACKNOWLEDGED - 1]["sha256"]
    finally:
        proc.kill9()


def append_torn_record(log) -> None:
    """Frame 10's append, torn by the crash: its header and part of its payload (any frame's size will do)."""
    payload = framelog.scan(log.read_bytes()).records[-1].payload
    with open(log, "ab") as f:
        f.write(framelog.encode(ACKNOWLEDGED, payload)[:framelog.HEADER.size + 4096])


def test_a_torn_tail_of_an_unacknowledged_append_is_cut_silently(killed, tmp_path, reference):
    size = (killed["all"] / LOG).stat().st_size
    with restarted(killed, "all", tmp_path, append_torn_record) as (proc, sid, log, _):
        stats = Client(proc.url).session(sid).stats()
        assert stats["frames"] == ACKNOWLEDGED and stats["state"] == "ok" and stats["archive_problem"] is None
        assert Client(proc.url).session(sid).digest()["sha256"] == reference[ACKNOWLEDGED]["sha256"]
        assert log.stat().st_size == size and not (log.parent / QUARANTINE).exists()
        assert "cutting off a torn log tail" in proc.log()
