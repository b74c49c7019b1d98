"""The session store in process (the HTTP tests drive it through a real service): the decode cache,
decoding (with the colour solve) outside the session's lock, so that folds go on while it runs, and
the frame log written while its frame folds: acknowledged after the fsync, undone when it fails."""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import os
import re
import shutil
import threading
import time

import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.datasets import load_tsdf_fusion
from canonical_core.decode import solve_colours, with_colour_offsets
from canonical_core.scene.decoding import decoded_rows
from client.cli import frame_arrays
from server import framelog, wire
from server.framelog import StorageError
from server.archive import payload_digest
from server.durability import restore_scene
from server.session_errors import FrameIdConflict, SessionUnavailable
from server.store import SessionStore

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
def test_a_colour_solve_session_serves_the_solved_decode(store, shelf_frames):
    session = store.create(SceneConfig(voxel_size=0.008, colour_solve={"views": 2}))
    for frame in shelf_frames[:3]:
        fold(session, frame)
    g, label_dim = session.gaussians()
    inputs = session.scene.decode_inputs()
    assert label_dim == 0 and len(inputs.views) == 2
    assert same(g, session.scene.decode())
    fused = session.scene.decode_from(inputs._replace(views=[]))  # the analytic decode
    assert same(g, solve_colours(fused, inputs.views)) and not same(g, fused)
    assert session.gaussians()[0] is g  # cached until the next fold
    assert session.stats()["gaussians"] == len(g)
    fewer, _ = session.gaussians(max_gaussians=len(g) // 2)
    assert len(fewer) == len(g) // 2 and same(fewer, session.scene.decode(len(g) // 2))


@pytest.mark.realdata
def test_a_colour_re_solve_runs_off_the_render_and_the_next_render_shows_it(store, shelf_frames):
    session = store.create(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "refresh": 1}))
    for frame in shelf_frames[:2]:
        fold(session, frame)
    session.gaussians()  # the first solve, in the call
    first = session.scene._decoding.solution
    fold(session, shelf_frames[2])
    shown, _ = session.gaussians()  # a re-solve is due: it goes to the colour-solve thread
    pending = session.scene.colour_solve_pending()
    assert pending is not None
    inputs = session.scene.decode_inputs()
    fused = session.scene.decode_from(inputs._replace(views=[]))
    rows = decoded_rows(inputs.sums, 0.0, session.config).rows
    assert same(shown, with_colour_offsets(fused, first.at(rows)))  # the render showed the last solution
    pending.result(timeout=300)
    assert session.scene._decoding.solution.frames == 3
    landed, _ = session.gaussians()
    assert not same(landed, shown) and same(landed, session.scene.decode())


@pytest.mark.realdata
def test_a_fold_goes_on_while_a_decode_runs_and_the_overtaken_decode_is_not_served(store, shelf_frames):
    session = store.create(SceneConfig(voxel_size=0.004, colour_solve={"views": 4, "scale": 1.0}))
    for frame in shelf_frames[:4]:
        fold(session, frame)
    before = len(session.scene.decode_from(session.scene.decode_inputs()._replace(views=[])))
    answer = {}
    render = threading.Thread(target=lambda: answer.update(g=session.gaussians()[0]))
    render.start()

    def solving() -> bool:
        """The decode lock held and the scene's lock free, seen twice 20 ms apart (so not the instant
        between taking the one and the other): the render is decoding and solving."""
        scene = session.scene
        if not (scene._decoding.lock.locked() and not scene._lock.locked() and not session.lock.locked()):
            return False
        time.sleep(0.02)
        return scene._decoding.lock.locked() and not scene._lock.locked() and not session.lock.locked()

    deadline = time.monotonic() + 120
    while not solving():
        assert time.monotonic() < deadline, "the render never decoded outside the scene's lock"
        time.sleep(0.005)
    fold(session, shelf_frames[4])  # takes the scene's lock: it would wait out the decode if the decode held it
    assert render.is_alive(), "the fold waited for the decode"
    render.join()

    assert len(answer["g"]) == before  # the render answered with the scene as it was asked
    current = session.gaussians()[0]  # after the fold: the overtaken solve was not cached
    assert len(current) != before
    assert same(current, session.scene.decode())


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
def test_a_retry_matches_a_frame_logged_under_the_older_digest(store, shelf_frames):
    """Sessions written before XXH3 hold BLAKE2b digests of their frames: a retry still matches them."""
    session = store.create(SceneConfig(voxel_size=0.008))
    payloads = [wire.pack(msgpack_frame({**frame_arrays(f), "frame_id": f"cam0/{k}"})) for k, f in enumerate(shelf_frames[:2])]
    report, replay = session.add_frame(payloads[0], wire.frame_from_message(wire.unpack(payloads[0])), 10**6, 1e9)
    known = session.frame_ids["cam0/0"]
    assert not replay and known.digest == payload_digest(payloads[0]) and known.digest.startswith("xxh3:")
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
