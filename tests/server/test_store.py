"""The session store in process (the HTTP tests drive it through a real service): the decode cache,
decoding (with the colour solve) outside the session's lock, so that folds go on while it runs, and
the frame log written while its frame folds: acknowledged after the fsync, undone when it fails."""

from __future__ import annotations

import dataclasses
import errno
import gc
import hashlib
import os
import re
import shutil
import threading
import time
import weakref

import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.datasets import load_tsdf_fusion
from canonical_core.scene import Scene
from client.cli.capture import frame_arrays
from server import framelog, wire
from server.framelog import StorageError
from server.digests import payload_digest
from server.durability import restore_scene
from server.session_errors import FrameIdConflict, SessionUnavailable
from server.store import SessionStore
from server.track import CAMERAS_FILE, ROW_BYTES, read_track

from ..conftest import solved_as_kept
from .harness import hold_snapshot_commits, msgpack_frame


def fold(session, frame) -> None:
    """What POST /frames does with a frame: its wire record logged, then folded."""
    payload = wire.pack(msgpack_frame(frame_arrays(frame)))
    session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 10**6, 1e9)


@pytest.fixture()
def store(tmp_path):
    store = SessionStore(tmp_path, max_sessions=4)
    store.open()
    yield store
    store.close()


@pytest.fixture(scope="module")
def shelf_frames(shelf_dir):
    return list(load_tsdf_fusion(shelf_dir, stride=8, max_frames=5))  # 640x480, about 10 degrees apart


def same(a, b) -> bool:
    return all(torch.equal(getattr(a, name), getattr(b, name)) for name in ("means", "scales", "quats", "opacities", "sh"))


def test_session_ids_are_hex_so_a_command_line_never_reads_one_as_a_flag(store):
    ids = [store.create(SceneConfig(voxel_size=0.01)).id for _ in range(4)]
    assert all(re.fullmatch(r"[0-9a-f]{32}", i) for i in ids) and len(set(ids)) == 4


@pytest.mark.realdata
def test_a_session_serves_its_last_colour_solution_and_solves_off_the_render(store, shelf_frames):
    session = store.create(SceneConfig(voxel_size=0.008, colour_solve={"views": 2}))
    for frame in shelf_frames[:3]:
        fold(session, frame)
    inputs = session.scene.decode_inputs()
    fused = session.scene.decode_from(inputs._replace(views=[]))  # the analytic decode
    g, label_dim = session.gaussians()  # no solution yet: the fused colours, and no solve in the call
    assert label_dim == 0 and len(inputs.views) == 2 and same(g, fused) and session.colour_solve_due()
    assert session.solve_colours() and not session.colour_solve_due()
    g = session.gaussians()[0]
    assert same(g, solved_as_kept(fused, inputs.views)) and not same(g, fused) and same(g, session.scene.decode())
    assert session.gaussians()[0] is g  # cached until the next fold
    assert session.stats()["gaussians"] == len(g)
    fewer, _ = session.gaussians(max_gaussians=len(g) // 2)
    assert len(fewer) == len(g) // 2 and same(fewer, session.scene.decode(len(g) // 2))


@pytest.mark.realdata
def test_a_fold_goes_on_while_a_colour_solve_runs(store, shelf_frames):
    session = store.create(SceneConfig(voxel_size=0.004, colour_solve={"views": 4, "scale": 1.0}))
    for frame in shelf_frames[:4]:
        fold(session, frame)
    scene = session.scene
    solver = threading.Thread(target=session.solve_colours)
    solver.start()

    def locked() -> bool:
        return scene._decoding.lock.locked() or scene._lock.locked() or session.lock.locked()

    deadline = time.monotonic() + 120
    while not locked():  # the solve copies and decodes the state under the locks ...
        assert time.monotonic() < deadline and solver.is_alive(), "the solve never took the decode lock"
        time.sleep(0.002)
    while locked() or (time.sleep(0.02) or locked()):  # ... then solves with none held (free twice, 20 ms apart)
        assert time.monotonic() < deadline and solver.is_alive(), "the solve never let go of the locks"
        time.sleep(0.002)
    fold(session, shelf_frames[4])  # takes the session's and the scene's locks: it would wait out a solve that held them
    assert solver.is_alive(), "the fold waited for the solve"
    solver.join()
    assert scene._decoding.solution.frames == 4 and session.colour_solve_due()  # the state it copied; due again
    plain = Scene(SceneConfig(voxel_size=0.004, colour_solve={"views": 0}))
    for frame in shelf_frames[:5]:
        plain.fold(frame)
    assert session.solve_colours()
    assert same(session.gaussians()[0], solved_as_kept(plain.decode(), scene._keyframes.frames()))


@pytest.mark.realdata
@pytest.mark.parametrize("retention", ["all", "none"])  # undo records roll the fold back; without, a rebuild from disk
def test_a_frame_whose_log_append_fails_while_it_folds_is_undone(store, shelf_frames, monkeypatch, retention):
    session = store.create(SceneConfig(voxel_size=0.008), retention=retention)
    for frame in shelf_frames[:2]:
        fold(session, frame)
    before = session.digest()
    real_write = os.write

    def disk_full(fd, data):
        if fd == session.log._fd:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(framelog.os, "write", disk_full)
    with pytest.raises(StorageError, match="No space left"):
        fold(session, shelf_frames[2])
    assert session.digest() == before and session.wedged is None
    monkeypatch.undo()
    fold(session, shelf_frames[2])  # the same frame, once there is space: folded as frame 2
    assert session.digest()["frames"] == 3 and len(framelog.scan(session.log.path.read_bytes()).records) == 3


@pytest.mark.realdata
def test_a_wedged_log_undoes_the_fold_and_refuses_the_next_frames(store, shelf_frames, monkeypatch):
    session = store.create(SceneConfig(voxel_size=0.008))
    fold(session, shelf_frames[0])
    before = session.digest()

    def failing(*args):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(framelog.os, "write", failing)
    monkeypatch.setattr(framelog.os, "ftruncate", failing)
    with pytest.raises(framelog.LogWedged):
        fold(session, shelf_frames[1])
    assert session.digest() == before and "Input/output error" in session.wedged
    with pytest.raises(SessionUnavailable):
        fold(session, shelf_frames[1])


@pytest.mark.realdata
def test_a_frame_is_acknowledged_only_after_its_record_is_fsynced(store, shelf_frames, monkeypatch):
    # the family named: a session that leaves it to its first frame also writes meta.json once then
    session = store.create(SceneConfig(voxel_size=0.008, sensor={"family": "structured_light"}))
    real_fsync, synced = os.fsync, []

    def slow_fsync(fd):  # a disk slower than the fold: the acknowledgement must wait for it
        time.sleep(0.5)
        real_fsync(fd)
        synced.append(time.monotonic())

    monkeypatch.setattr(framelog.os, "fsync", slow_fsync)
    fold(session, shelf_frames[0])
    acknowledged = time.monotonic()
    assert len(synced) == 1 and synced[0] <= acknowledged


@pytest.mark.realdata
def test_the_frame_id_table_keeps_the_latest_reports_and_still_knows_older_frames(store, shelf_frames, monkeypatch):
    """A long stream's table holds a whole fold report for its latest frames only (it is written into
    every checkpoint): an older frame's retry is still a replay, answered with its index and zero
    counts, through a restart too."""
    from server import frame_ids

    monkeypatch.setattr(frame_ids, "REPORTS_KEPT", 2)
    session = store.create(SceneConfig(voxel_size=0.008))
    payloads = [wire.pack(msgpack_frame({**frame_arrays(f), "frame_id": f"cam0/{k}"})) for k, f in enumerate(shelf_frames[:4])]
    reports = [session.add_frame(p, wire.frame_from_message(wire.unpack(p)), 10**6, 1e9)[0] for p in payloads]
    assert [session.frame_ids[f"cam0/{k}"].report is not None for k in range(4)] == [False, False, True, True]
    for restarted in (False, True):
        if restarted:
            session.snapshot()
            store.close()
            store.open()
            session = store.get(session.id)
        old, replay = session.add_frame(payloads[0], wire.frame_from_message(wire.unpack(payloads[0])), 10**6, 1e9)
        assert replay and (old.frame_index, old.new_voxels) == (0, 0) and reports[0].new_voxels > 0
        latest, replay = session.add_frame(payloads[3], wire.frame_from_message(wire.unpack(payloads[3])), 10**6, 1e9)
        assert replay and latest == reports[3]
        assert session.scene.frames == 4


@pytest.mark.realdata
def test_the_time_of_a_deleted_sessions_last_fold_goes_with_it(store, shelf_frames):
    """The event hub remembers each session's last fold (the viewer shows its age): a service that
    makes and deletes sessions for months must not keep one entry for every session it ever had."""
    from server.events import FoldEvents

    events = FoldEvents(4, 16)
    session = store.create(SceneConfig(voxel_size=0.01))
    payload = wire.pack(msgpack_frame(frame_arrays(shelf_frames[0])))
    frame = wire.frame_from_message(wire.unpack(payload))
    report, _ = session.add_frame(payload, frame, 10**6, 1e9)
    events.folded(session, frame.camera, report)
    assert abs(events.last_fold_time(session) - time.time()) < 60 and len(events.last_fold) == 1
    assert store.delete(session.id)
    del session
    gc.collect()
    store.release_departed()
    assert len(events.last_fold) == 0


@pytest.mark.realdata
def test_a_retry_matches_a_frame_logged_under_the_older_digest(store, shelf_frames):
    """Sessions written before XXH3 hold BLAKE2b digests of their frames: a retry still matches them."""
    session = store.create(SceneConfig(voxel_size=0.008))
    payloads = [wire.pack(msgpack_frame({**frame_arrays(f), "frame_id": f"cam0/{k}"})) for k, f in enumerate(shelf_frames[:2])]
    report, replay = session.add_frame(payloads[0], wire.frame_from_message(wire.unpack(payloads[0])), 10**6, 1e9)
    known = session.frame_ids["cam0/0"]
    assert not replay and known.digest == payload_digest(payloads[0]) and known.digest.startswith("xxh3m:")
    session.frame_ids["cam0/0"] = dataclasses.replace(known, digest=hashlib.blake2b(payloads[0], digest_size=16).hexdigest())
    again, replay = session.add_frame(payloads[0], wire.frame_from_message(wire.unpack(payloads[0])), 10**6, 1e9)
    assert replay and again == report and session.scene.frames == 1
    other = wire.pack(msgpack_frame({**frame_arrays(shelf_frames[1]), "frame_id": "cam0/0"}))
    with pytest.raises(FrameIdConflict, match="frame_id"):
        session.add_frame(other, wire.frame_from_message(wire.unpack(other)), 10**6, 1e9)
    assert session.scene.frames == 1


@pytest.mark.realdata
def test_a_due_snapshot_is_written_off_the_acknowledged_path_and_a_crash_before_its_commit_loses_nothing(
        store, shelf_frames, monkeypatch, tmp_path):
    """The frame that makes a snapshot due is answered before the snapshot is written, and frames fold
    on meanwhile. The files as a crash before the commit leaves them (the snapshot's own file written,
    not yet the snapshot) restore every frame; after the commit the log holds only the frames after it."""
    written, release = hold_snapshot_commits(monkeypatch)
    session = store.create(SceneConfig(voxel_size=0.01))
    payloads = [wire.pack(msgpack_frame(frame_arrays(f))) for f in shelf_frames[:3]]
    for payload in payloads[:2]:  # the second frame makes a snapshot due (every 2 frames)
        session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 2, 1e9)
    assert written.wait(60)
    session.add_frame(payloads[2], wire.frame_from_message(wire.unpack(payloads[2])), 2, 1e9)  # folds meanwhile
    assert session.snapshots.frames == 0 and session.scene.frames == 3
    crashed = tmp_path / "crashed" / session.id
    shutil.copytree(session.path, crashed)  # the files as a kill -9 now would leave them
    with open(crashed / CAMERAS_FILE, "r+b") as track:  # and the kill came before the last frame's camera row
        track.truncate(2 * ROW_BYTES)
    release.set()
    session.snapshots.wait()
    assert session.snapshots.frames == 2 and session.snapshots.error is None
    records = framelog.scan((session.path / "frames.log").read_bytes()).records
    assert [(r.checkpoint, r.index) for r in records] == [(True, 2), (False, 2)]
    assert not list(session.path.glob("scene.snap.*"))  # the pending file became the snapshot
    digest = session.scene.digest()
    for path in (session.path, crashed):
        restored = restore_scene(path, session.config)
        restored.log.close()
        assert restored.scene.frames == 3 and restored.scene.digest() == digest
    assert restored.snapshot_frames == 0 and not list(crashed.glob("scene.snap.*.next*"))  # dropped on start
    assert read_track(crashed / CAMERAS_FILE, 3)[:, 0].tolist() == [0, 1, 2]  # the replay wrote the missing row


def test_a_session_a_job_holds_at_its_deletion_goes_back_at_the_first_release_after_the_job_lets_go(store, shelf_frames):
    alone = store.create(SceneConfig(voxel_size=0.01)).id
    fold(store.get(alone), shelf_frames[0])
    deleted = store.delete(alone)  # outside an assert: pytest's rewriting would hold the session
    assert deleted and store.release_departed() == 0  # nothing held it: nothing pending
    held = store.create(SceneConfig(voxel_size=0.01))  # this reference stands for a render in flight
    fold(held, shelf_frames[0])
    freed = weakref.ref(held)
    gc.disable()  # only the store's release may free it: no collection happens by chance
    try:
        assert store.delete(held.id)
        assert store.release_departed() == 1 and freed() is not None  # still held
        del held
        assert store.release_departed() == 0 and freed() is None
    finally:
        gc.enable()
