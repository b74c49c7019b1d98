"""Nothing acknowledged is lost, and an error tells the truth: a full disk, a damaged log, a snapshot
that cannot be written, files removed by hand, two servers on one directory, and retried frames, each
on a real service process and real files."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import time

import httpx
import msgpack
import pytest

from client.sdk import Client
from server import framelog

from .harness import REPO, VOXEL, ServerProcess, msgpack_frame, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]
MSGPACK = {"content-type": "application/msgpack"}


def server(tmp_path, data, **settings) -> ServerProcess:
    settings = {"snapshot_every_seconds": 3600, "snapshot_every_frames": 1000, "warm_up": "false", **settings}
    return ServerProcess(data, tmp_path / "server.log", **settings)


def log_of(data, sid):
    return data / "sessions" / sid / "frames.log"


def post(proc: ServerProcess, sid: str, kwargs: dict) -> httpx.Response:
    return httpx.post(f"{proc.url}/v1/sessions/{sid}/frames", content=msgpack.packb(msgpack_frame(kwargs)),
                      headers=MSGPACK, timeout=120)


def new_session(proc: ServerProcess, frames: list[dict], **settings) -> str:
    """The id of a new session on ``proc`` (its ``settings``) that has folded ``frames`` (each acknowledged)."""
    session = Client(proc.url).create_session(voxel_size=VOXEL, **settings)
    for kwargs in frames:
        session.add_frame(**kwargs)
    return session.id


@contextlib.contextmanager
def serving(proc: ServerProcess):
    """``proc`` started; its log printed if the test fails; killed at the end."""
    try:
        yield proc.start()
    except BaseException:
        print(proc.log())
        raise
    finally:
        proc.kill9()


@pytest.fixture()
def tmpfs(tmp_path):
    """A 6 MiB tmpfs: a disk that really fills up (needs root to mount)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root; test_framelog covers the full disk at the write call")
    mount = tmp_path / "small_disk"
    mount.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(mount)], check=True)
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


def test_a_full_disk_refuses_frames_with_507_and_loses_nothing_acknowledged(tmp_path, tmpfs, frames, reference):
    data = tmpfs / "data"
    with serving(server(tmp_path, data)) as proc:
        sid = Client(proc.url).create_session(voxel_size=VOXEL).id
        for kwargs in frames[:2]:
            assert post(proc, sid, kwargs).status_code == 200
        # fill the disk, leaving less than one frame record
        free = shutil.disk_usage(tmpfs).free
        record = len(msgpack.packb(msgpack_frame(frames[2])))
        with open(tmpfs / "filler", "wb") as f:
            f.write(b"\0" * (free - record // 2))
        size = log_of(data, sid).stat().st_size
        for kwargs in frames[2:4]:
            r = post(proc, sid, kwargs)
            assert r.status_code == 507, r.text
            assert r.json()["error"]["field"] == "data_dir" and "No space left" in r.json()["error"]["message"]
        # the partial records were cut at once: the log holds exactly the two acknowledged frames
        found = framelog.scan(log_of(data, sid).read_bytes())
        assert log_of(data, sid).stat().st_size == size and found.end == found.size and len(found.records) == 2
        assert Client(proc.url).session(sid).digest()["frames"] == 2
        assert "canonical_storage_errors_total 2" in httpx.get(f"{proc.url}/metrics").text
        assert proc.log().count(f"/v1/sessions/{sid}/frames: frames.log: cannot append a record: No space left") == 2
        # space again: the same frames are taken, then a crash
        (tmpfs / "filler").unlink()
        for kwargs in frames[2:4]:
            assert post(proc, sid, kwargs).status_code == 200
        proc.kill9()
        proc.start()
        digest = Client(proc.url).session(sid).digest()
        assert digest["frames"] == 4 and digest["sha256"] == reference[4]["sha256"]


def test_a_restart_on_a_disk_still_full_serves_the_scene_and_reports_the_archive(tmp_path, tmpfs, frames, reference):
    with serving(server(tmp_path, tmpfs / "data")) as proc:
        sid = new_session(proc, frames[:2])
        assert wait_for(lambda: Client(proc.url).session(sid).stats()["archive_frames"] == 2)  # archived off the path
        # room for the frame's log record (and 64 KiB), not for its archived copy (zstd: about 40% of it)
        record = len(msgpack.packb(msgpack_frame(frames[2])))
        with open(tmpfs / "filler", "wb") as f:
            f.write(b"\0" * (shutil.disk_usage(tmpfs).free - record - 65536))
        assert post(proc, sid, frames[2]).status_code == 200
        assert wait_for(lambda: Client(proc.url).session(sid).stats()["archive_problem"])
        proc.kill9()
        proc.start()  # the disk is still full: the frame cannot be archived from the log
        session = Client(proc.url).session(sid)
        digest, stats = session.digest(), session.stats()
        assert digest["frames"] == 3 and digest["sha256"] == reference[3]["sha256"]
        assert "No space left" in stats["archive_problem"]
        (tmpfs / "filler").unlink()
        proc.kill9()
        proc.start()  # space again: the restart archives it, and corrections are served
        assert Client(proc.url).session(sid).stats()["archive_problem"] is None


def test_a_damaged_log_is_kept_quarantined_and_refused_until_repair(tmp_path, frames, reference):
    data = tmp_path / "data"
    with serving(server(tmp_path, data)) as proc:
        sid = new_session(proc, frames[:6], archive_retention="none")  # no second copy (test_log_damage.py has one)
        healthy = new_session(proc, frames[:2])  # frames its snapshot lacks: a listing snapshots no session
        proc.kill9()
        damaged = bytearray(log_of(data, sid).read_bytes())
        third = framelog.scan(bytes(damaged)).records[2]
        damaged[third.offset + framelog.HEADER.size + 100] ^= 0xFF
        log_of(data, sid).write_bytes(bytes(damaged))

        proc.start()
        r = httpx.get(f"{proc.url}/v1/sessions/{sid}")
        assert r.status_code == 409 and r.json()["error"]["code"] == "session_unavailable"
        assert "damaged record" in r.json()["error"]["message"] and "canonical repair" in r.json()["error"]["message"]
        assert httpx.post(f"{proc.url}/v1/sessions/{sid}/frames", content=b"x", headers=MSGPACK).status_code == 409
        listed = {s["id"]: s for s in httpx.get(f"{proc.url}/v1/sessions").json()["sessions"]}
        assert listed[sid]["state"] == "unavailable" and listed[sid]["frames"] is None
        table = subprocess.run([sys.executable, "-m", "client.cli", "sessions", "--url", proc.url], cwd=REPO,
                               capture_output=True, text=True, timeout=120)  # the problem under the table
        assert any(line.startswith(f"{sid}: ") and "damaged record" in line for line in table.stdout.splitlines())
        assert "canonical_sessions_unavailable 1" in httpx.get(f"{proc.url}/metrics").text
        assert log_of(data, sid).read_bytes() == bytes(damaged)  # never cut
        copies = list((data / "sessions" / sid / "quarantine").iterdir())
        assert [c.read_bytes() for c in copies] == [bytes(damaged)]

        # repair needs the service stopped: the directory is locked while it runs
        cli = [sys.executable, "-m", "client.cli", "repair", "--data-dir", str(data)]
        busy = subprocess.run(cli, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert busy.returncode == 1 and "in use by another server" in busy.stderr
        proc.kill9()
        listing = subprocess.run(cli, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert listing.returncode == 0 and sid in listing.stdout and "1 of 2 sessions need repair" in listing.stdout
        assert not (data / "sessions" / healthy / "scene.snap").exists()
        asked = subprocess.run(cli + ["--session", sid], cwd=REPO, capture_output=True, text=True, timeout=300)
        assert asked.returncode == 1 and asked.stderr.startswith("error: action:") and "Traceback" not in asked.stderr
        fixed = subprocess.run(cli + ["--session", sid, "--action", "skip"], cwd=REPO, capture_output=True, text=True, timeout=300)
        assert fixed.returncode == 0 and "now holds 5 frames" in fixed.stdout, fixed.stdout + fixed.stderr

        proc.start()
        assert Client(proc.url).session(sid).digest()["frames"] == 5


def test_truncate_repair_serves_the_frames_before_the_damage(tmp_path, frames, reference):
    from server.store import SessionStore

    data = tmp_path / "data"
    with serving(server(tmp_path, data)) as proc:
        sid = new_session(proc, frames[:4], archive_retention="none")
    damaged = bytearray(log_of(data, sid).read_bytes())
    damaged[framelog.scan(bytes(damaged)).records[2].offset + 5] ^= 0x01  # frame 2's length field
    log_of(data, sid).write_bytes(bytes(damaged))
    store = SessionStore(data, max_sessions=8)
    try:
        assert "now holds 2 frames" in store.repair(sid, "truncate")
    finally:
        store.close()
    store = SessionStore(data, max_sessions=8)
    store.open()
    try:
        assert store.get(sid).digest()["sha256"] == reference[2]["sha256"]
    finally:
        store.close()


def test_a_snapshot_that_cannot_be_written_is_no_error_of_the_frame(tmp_path, frames, reference):
    data = tmp_path / "data"
    with serving(server(tmp_path, data, snapshot_every_frames=1)) as proc:
        sid = new_session(proc, frames[:1])
        session = Client(proc.url).session(sid)
        assert wait_for(lambda: session.stats()["snapshot_frames"] == 1)  # written off the acknowledged path
        # the snapshots' temp files cannot be created (as root too, unlike chmod): the one written now and
        # those written off the acknowledged path, numbered per session
        blockers = [data / "sessions" / sid / name for name in ("scene.snap.tmp", "scene.snap.2.next.tmp",
                                                                "scene.snap.3.next.tmp")]
        for blocker in blockers:
            blocker.mkdir()
        for kwargs in frames[1:3]:
            assert post(proc, sid, kwargs).status_code == 200  # the truth: folded and durable in the log
        assert wait_for(lambda: session.stats()["snapshot_error"] is not None)
        stats = session.stats()
        assert stats["frames"] == 3 and stats["snapshot_frames"] == 1 and "scene.snap" in stats["snapshot_error"]
        assert "canonical_snapshot_failures 1" in httpx.get(f"{proc.url}/metrics").text
        proc.kill9()
        for blocker in blockers:
            blocker.rmdir()
        proc.start()
        digest = Client(proc.url).session(sid).digest()
        assert digest["frames"] == 3 and digest["sha256"] == reference[3]["sha256"]


def test_files_removed_by_hand_are_loud_and_one_server_holds_a_directory(tmp_path, frames):
    data = tmp_path / "data"
    with serving(server(tmp_path, data, snapshot_every_frames=2)) as proc:
        ids = [new_session(proc, frames[:3]) for _ in range(3)]  # a snapshot at 2 frames, one frame in the log after it
        ids.append(new_session(proc, frames[:3], archive_retention="none"))  # no second copy of its frames
        ids.append(new_session(proc, frames[:3]))
        assert all(wait_for(lambda: Client(proc.url).session(sid).stats()["snapshot_frames"] == 2) for sid in ids)
        digest = Client(proc.url).session(ids[0]).digest()["sha256"]

        second = server(tmp_path / "second", data)
        (tmp_path / "second").mkdir()
        with pytest.raises(RuntimeError):
            second.start(timeout=60)
        assert "in use by another server" in second.log() and f"pid {proc.proc.pid}" in second.log()
        assert second.proc.returncode != 0

        proc.kill9()
        for sid in (ids[0], ids[3]):
            (data / "sessions" / sid / "scene.snap").unlink()
        (data / "sessions" / ids[1] / "frames.log").unlink()
        (data / "sessions" / ids[2] / "meta.json").unlink()
        (data / "sessions" / ids[4] / "meta.json").write_text("{garbled")
        proc.start()
        problems = {s["id"]: s["problem"] for s in httpx.get(f"{proc.url}/v1/sessions").json()["sessions"]}
        # the frames the snapshot held are in the frame archive: folded again from it, as they were
        assert problems[ids[0]] is None and Client(proc.url).session(ids[0]).digest()["sha256"] == digest
        assert "scene.snap is missing" in problems[ids[3]] and "frames 0..1 are not on disk" in problems[ids[3]]
        assert "frames.log is missing" in problems[ids[1]]
        assert "meta.json is missing" in problems[ids[2]]
        assert problems[ids[4]].startswith("meta.json: not valid JSON") and "Traceback" not in proc.log()
        assert all((data / "sessions" / sid).is_dir() for sid in ids)  # nothing removed
        # an operator may delete an unavailable session
        assert httpx.delete(f"{proc.url}/v1/sessions/{ids[2]}").status_code == 200
        assert not (data / "sessions" / ids[2]).exists()


def test_settings_edited_in_meta_json_are_refused_until_put_back(tmp_path, frames):
    data = tmp_path / "data"
    with serving(server(tmp_path, data, snapshot_every_frames=2)) as proc:
        snapped = new_session(proc, frames[:3])  # a snapshot at 2 frames, one frame in the log after it
        logged = new_session(proc, frames[:1])  # no snapshot: the log alone
        assert wait_for(lambda: Client(proc.url).session(snapped).stats()["snapshot_frames"] == 2)
        proc.kill9()
        metas = {sid: data / "sessions" / sid / "meta.json" for sid in (snapped, logged)}
        written = {sid: path.read_text() for sid, path in metas.items()}
        for sid, path in metas.items():
            assert f'"voxel_size": {VOXEL}' in written[sid]
            path.write_text(written[sid].replace(f'"voxel_size": {VOXEL}', '"voxel_size": 0.02'))
        files = {p: p.read_bytes() for p in data.rglob("*") if p.is_file() and p.name != ".lock"}

        proc.start()
        problems = {s["id"]: s.get("problem") or "served" for s in httpx.get(f"{proc.url}/v1/sessions").json()["sessions"]}
        assert f"meta.json: config.voxel_size is 0.02, but scene.snap was made with {VOXEL}" in problems[snapped]
        assert "meta.json: config was changed after the session was created" in problems[logged]
        for sid in (snapped, logged):
            r = httpx.get(f"{proc.url}/v1/sessions/{sid}")
            assert r.status_code == 409 and "meta.json" in r.json()["error"]["message"]
        proc.kill9()
        cli = [sys.executable, "-m", "client.cli", "repair", "--data-dir", str(data), "--session", snapped, "--action", "skip"]
        refused = subprocess.run(cli, cwd=REPO, capture_output=True, text=True, timeout=300)
        assert refused.returncode == 1 and refused.stderr.startswith("error: meta.json: config.voxel_size"), refused.stderr
        assert {p: p.read_bytes() for p in files} == files  # nothing changed, nothing quarantined
        assert not any((data / "sessions" / sid / "quarantine").exists() for sid in metas)

        for sid, path in metas.items():
            path.write_text(written[sid])
        proc.start()
        assert [Client(proc.url).session(sid).stats()["frames"] for sid in (snapped, logged)] == [3, 1]


def test_a_retried_frame_is_folded_once_across_a_restart(tmp_path, frames, reference):
    data = tmp_path / "data"
    with serving(server(tmp_path, data, snapshot_every_frames=2)) as proc:
        sid = Client(proc.url).create_session(voxel_size=VOXEL).id
        tagged = [{**kwargs, "frame_id": f"cam0/{k}"} for k, kwargs in enumerate(frames[:3])]
        first = [post(proc, sid, kwargs) for kwargs in tagged]
        assert [r.status_code for r in first] == [200] * 3
        again = post(proc, sid, tagged[2])  # the answer was lost; the client sends it again
        assert again.status_code == 200 and again.headers["idempotent-replay"] == "true"
        assert again.json() == first[2].json()
        assert Client(proc.url).session(sid).digest()["frames"] == 3
        other = post(proc, sid, {**tagged[1], "frame_id": "cam0/0"})
        assert other.status_code == 409 and other.json()["error"]["field"] == "frame_id"

        proc.kill9()  # frames 0-1 in the snapshot (their ids in the log's checkpoint), frame 2 in the log
        proc.start()
        for k in (0, 2):  # frame 2's report comes from the replay of the log: the same fold, its own timing
            r = post(proc, sid, tagged[k])
            assert r.status_code == 200 and r.headers["idempotent-replay"] == "true"
            assert {**r.json(), "ms": 0} == {**first[k].json(), "ms": 0}
        digest = Client(proc.url).session(sid).digest()
        assert digest["frames"] == 3 and digest["sha256"] == reference[3]["sha256"]  # ids do not change the scene
