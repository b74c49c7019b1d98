"""The store's corrections on real files, in-process: a correction of recent frames rolls the served
scene back in place, or starts from the state a previous correction kept, and equals the full re-fold."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from canonical_core import SceneConfig
from canonical_core.scene.undo import MAX_UNDO_SHARE, MIN_KEPT
from canonical_wire import encode_array, pack
from client.cli.capture import frame_arrays
from server import corrections, wire
from server import session as session_module
from server.archive import ARCHIVE
from server.payloads import DamagedFrame
from server.corrections import BASE
from server.session_errors import CorrectionRefused
from server.track import CAMERAS_FILE, read_track
from server.store import SessionStore

from .harness import hold_snapshot_commits

pytestmark = pytest.mark.realdata
CONFIG = SceneConfig(voxel_size=0.01)


def payload(kwargs: dict, c2w=None) -> tuple[bytes, object]:
    msg = {"rgb": encode_array(kwargs["rgb"]), "K": kwargs["K"].tolist(), "depth": encode_array(kwargs["depth"]),
           "c2w": (kwargs["c2w"] if c2w is None else c2w).tolist(), "frame_id": kwargs["frame_id"]}
    return pack(msg), wire.frame_from_message(msg)


@pytest.fixture(scope="module")
def shelf(shelf_dir) -> list[dict]:
    from canonical_core.datasets import load_tsdf_fusion

    return [frame_arrays(f, 0.25) for f in load_tsdf_fusion(shelf_dir, stride=5, max_frames=7)]


def streamed(store: SessionStore, frames: list[dict], poses: dict | None = None, snapshot_every: int = 1000):
    session = store.create(CONFIG)
    for k, kwargs in enumerate(frames):
        session.add_frame(*payload(kwargs, (poses or {}).get(k)), snapshot_every, 3600)
        session.snapshots.wait()  # a due snapshot is written off the fold's path: as a stream's pause would
    return session


def damage_first_frame(session) -> None:
    """Zero some bytes of frame 0's archived message: a re-fold that read it again would fail."""
    session.archive.flush()  # the writer thread appends deferred frames: rewrite the file after it
    archive = session.path / ARCHIVE
    data = bytearray(archive.read_bytes())
    entry = session.archive.entries[0]
    data[entry.offset + 10: entry.offset + 20] = bytes(10)
    archive.write_bytes(bytes(data))


def test_a_correction_of_recent_frames_starts_from_the_kept_state(tmp_path, shelf, monkeypatch):
    monkeypatch.setattr(corrections, "BASE_EVERY", 2)
    monkeypatch.setattr(session_module, "UNDO_DEPTH", 0)  # no roll-back in place: the re-fold from saved states
    store = SessionStore(tmp_path, 8)
    store.open()
    try:
        shift = np.zeros((4, 4))
        shift[:3, 3] = 0.01
        moved = {k: kw["c2w"] + shift for k, kw in enumerate(shelf)}  # every frame 1.7 cm off
        session = streamed(store, shelf, moved)
        session.corrections.correct({kw["frame_id"]: kw["c2w"] for kw in shelf[:2]})  # touches frame 0: a full re-fold
        assert (session.path / BASE).is_file() and session.snapshots.frames == len(shelf)
        damage_first_frame(session)
        session.corrections.correct({shelf[6]["frame_id"]: shelf[6]["c2w"]})  # starts from the kept state after 6 frames
        session.corrections.correct({shelf[6]["frame_id"]: moved[6]})  # and again: that state is kept on
        session.corrections.correct({shelf[6]["frame_id"]: shelf[6]["c2w"]})
        expected = streamed(store, shelf, {k: moved[k] for k in (2, 3, 4, 5)})
        assert session.digest()["sha256"] == expected.digest()["sha256"]
        with pytest.raises(DamagedFrame):  # frame 5 lies before every kept state: frame 0 is read, and it is damaged
            session.corrections.correct({shelf[5]["frame_id"]: shelf[5]["c2w"]})
        assert session.digest()["sha256"] == expected.digest()["sha256"]  # and nothing changed
    finally:
        store.close()


def test_the_snapshot_a_correction_started_from_is_kept_for_the_next(tmp_path, shelf, monkeypatch):
    monkeypatch.setattr(corrections, "BASE_EVERY", 4)
    monkeypatch.setattr(session_module, "UNDO_DEPTH", 0)  # no roll-back in place: the re-fold from saved states
    store = SessionStore(tmp_path, 8)
    store.open()
    try:
        session = streamed(store, shelf, snapshot_every=3)
        assert session.snapshots.frames == 6
        damage_first_frame(session)
        other = np.eye(4)
        other[:3, 3] = [0.01, 0.0, 0.0]
        session.corrections.correct({shelf[6]["frame_id"]: other @ shelf[6]["c2w"]})  # from the snapshot of 6 frames
        assert session.snapshots.frames == 7  # the snapshot now holds the corrected scene
        session.corrections.correct({shelf[6]["frame_id"]: shelf[6]["c2w"]})  # from the state after 6 frames, kept
        assert session.digest()["sha256"] == streamed(store, shelf).digest()["sha256"]
    finally:
        store.close()


def reopened(store: SessionStore, tmp_path, **options) -> SessionStore:
    """The data directory opened afresh as a restart after a kill -9 would: no snapshot on the way out.
    ``options``: the new store's settings (its attributes, as the app sets them)."""
    os.close(store._dir_lock)
    store._dir_lock = None
    again = SessionStore(tmp_path, 8)
    for name, value in options.items():
        setattr(again, name, value)
    again.open()
    return again


@pytest.mark.parametrize("snapshot_every, touch", [(1000, 5), (3, 6), (3, 4)])
def test_a_correction_of_recent_frames_rolls_back_in_place_and_survives_a_restart(tmp_path, shelf, snapshot_every, touch):
    """(1000, 5) and (3, 6): after the snapshot's frames, so the log is rewritten and no snapshot is
    taken; (3, 4): before them, so the corrected scene is snapshotted."""
    store = SessionStore(tmp_path, 8)
    store.open()
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    session = streamed(store, shelf, {k: shift @ kw["c2w"] for k, kw in enumerate(shelf)}, snapshot_every)
    snapshot_frames = session.snapshots.frames
    damage_first_frame(session)  # a correction that re-read frame 0 would fail
    done = session.corrections.correct({kw["frame_id"]: kw["c2w"] for kw in shelf[touch:]}, [shelf[touch]["frame_id"]])
    assert (done["frames"], done["corrected"], done["removed"]) == (len(shelf) - 1, len(shelf) - touch - 1, 1)
    expected = [kw if k > touch else {**kw, "c2w": shift @ kw["c2w"]} for k, kw in enumerate(shelf) if k != touch]
    digest = streamed(store, expected).digest()["sha256"]
    assert session.digest()["sha256"] == digest
    assert session.snapshots.frames == (snapshot_frames if touch >= snapshot_frames else len(shelf) - 1)
    again = reopened(store, tmp_path)
    try:
        restored = again.get(session.id)
        assert restored.digest()["sha256"] == digest
        k = touch + 1 if touch + 1 < len(shelf) else touch - 1  # a frame whose log record was rewritten, if any
        retry = shelf[k]  # a retry of an acknowledged frame, as first sent, is recognised
        report, replay = restored.add_frame(*payload(retry, shift @ retry["c2w"]), 1000, 3600)
        assert replay and report.frame_index == (k - 1 if k > touch else k)
        assert restored.digest()["sha256"] == digest
    finally:
        again.close()


@pytest.mark.parametrize("touch", [5, 1], ids=["recent frames, in place", "a re-fold"])
def test_a_kill_after_a_correction_is_archived_restores_its_camera_track_too(tmp_path, shelf, monkeypatch, touch):
    """The correction archived, then the process dies before the track and the files caught up: the
    restart re-folds the archive, and the viewer's track shows the corrected poses without the removed frame."""
    store = SessionStore(tmp_path, 8)
    store.open()
    session = streamed(store, shelf)
    cameras = read_track(session.path / CAMERAS_FILE, len(shelf))
    monkeypatch.setattr(corrections, "correct_track", lambda *args: None)  # killed before any of them
    monkeypatch.setattr(corrections.Corrections, "_rewrite_log", lambda *args: None)
    monkeypatch.setattr(corrections.Corrections, "_persist", lambda *args: None)
    moved = shelf[touch + 1]["c2w"].copy()
    moved[:3, 3] += 0.02
    session.corrections.correct({shelf[touch + 1]["frame_id"]: moved}, [shelf[touch]["frame_id"]])
    assert np.array_equal(read_track(session.path / CAMERAS_FILE, len(shelf)), cameras)  # stale, as a kill leaves it
    monkeypatch.undo()
    again = reopened(store, tmp_path)
    try:
        restored = again.get(session.id)
        track = read_track(restored.path / CAMERAS_FILE, restored.scene.frames)
        expected = np.delete(cameras, touch, axis=0)
        expected[:, 0] = np.arange(len(shelf) - 1)
        expected[touch, 7:] = moved.reshape(16)
        assert restored.scene.frames == len(shelf) - 1 and np.allclose(track, expected)
    finally:
        again.close()


def held_background_correction(monkeypatch, store: SessionStore, shelf: list[dict], remove: list) -> tuple:
    """A session of the shelf's first 5 frames, their poses shifted 1 cm, and a background correction
    of them back to the capture's poses (``remove``: frames it removes too) whose re-fold has started
    and waits: (session, its answer, the gate that lets the re-fold go on)."""
    started, gate = threading.Event(), threading.Event()
    real = corrections.counted

    def gated(frames, job):  # the background re-fold waits here until the test lets it go
        started.set()
        gate.wait(120)
        yield from real(frames, job)

    monkeypatch.setattr(corrections, "counted", gated)
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    session = streamed(store, shelf[:5], {k: shift @ kw["c2w"] for k, kw in enumerate(shelf)})
    done = session.corrections.correct({kw["frame_id"]: kw["c2w"] for kw in shelf[:5]}, remove, wait=False)
    assert started.wait(120)
    return session, done, gate


def finished(session, correction_id: str) -> dict:
    """The status of a background correction once it is no longer running (at most 2 minutes)."""
    for _ in range(600):
        status = session.corrections.status(correction_id)
        if status["state"] != "running":
            return status
        time.sleep(0.2)
    return status


def test_a_background_correction_catches_up_on_frames_that_arrive_meanwhile(tmp_path, shelf, monkeypatch):
    """``wait=False``: the correction is archived and answered at once; frames sent while it re-folds
    fold into the served (old) scene, and the re-fold catches up on them before the swap, so the
    corrected scene equals the corrected stream folded afresh; a second correction meanwhile is refused."""
    store = SessionStore(tmp_path, 8)
    store.open()
    session, done, gate = held_background_correction(monkeypatch, store, shelf, [shelf[1]["frame_id"]])
    assert done["state"] == "pending" and done["frames"] == 5
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    for kwargs in shelf[5:]:  # folded into the old scene meanwhile, not refused
        session.add_frame(*payload(kwargs), 1000, 3600)
    old = streamed(store, [{**kw, "c2w": shift @ kw["c2w"]} for kw in shelf[:5]] + shelf[5:]).digest()["sha256"]
    assert session.digest()["sha256"] == old
    with pytest.raises(CorrectionRefused, match=done["correction_id"]):
        session.corrections.correct({shelf[0]["frame_id"]: shelf[0]["c2w"]})
    assert session.corrections.status(done["correction_id"])["state"] == "running"
    gate.set()
    status = finished(session, done["correction_id"])
    assert status["state"] == "done" and status["refolded"] == status["total"] == len(shelf) - 1, status
    assert status["result"]["frames"] == len(shelf) - 1
    expected = streamed(store, shelf[:1] + shelf[2:]).digest()["sha256"]
    assert session.digest()["sha256"] == expected
    again = reopened(store, tmp_path)
    try:
        assert again.get(session.id).digest()["sha256"] == expected
        assert again.get(session.id).corrections.status(done["correction_id"])["state"] == "done"
        with pytest.raises(KeyError):
            again.get(session.id).corrections.status("nope")
    finally:
        again.close()


def test_a_frame_the_archive_cannot_take_during_a_background_correction_is_refused_not_lost(tmp_path, shelf,
                                                                                            monkeypatch):
    """The scene a background correction swaps in is made of the archive's frames: a frame folded
    meanwhile that the archive cannot take (a full disk) is taken back and refused (507, nothing
    applied), and so are the frames after it until the correction ends, instead of being acknowledged
    and then dropped by the swap (and by the restart, which re-folds the archive)."""
    import errno

    from server.framelog import StorageError

    store = SessionStore(tmp_path, 8)
    store.open()
    session, done, gate = held_background_correction(monkeypatch, store, shelf, [])
    before = session.digest()["sha256"]

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(session.archive, "append_frame", full)
    # were the refused frame's log record not to be cut off either, its fold is still taken back, and
    # the session takes no more frames until a restart reads its log
    truncate = session.log.truncate
    session.log.truncate = lambda offset: (_ for _ in ()).throw(OSError(errno.EIO, "I/O error"))
    with pytest.raises(StorageError):
        session.add_frame(*payload(shelf[5]), 1000, 3600)
    assert session.scene.frames == 5 and session.digest()["sha256"] == before and "could not be cut off" in session.wedged
    session.log.truncate, session.wedged = truncate, None  # (as a restart would: the rest of the story below)
    for kwargs in shelf[5:]:
        with pytest.raises(StorageError) as refused:
            session.add_frame(*payload(kwargs), 1000, 3600)
        assert refused.value.full  # a full disk: 507, retry later
    assert session.scene.frames == 5 and session.digest()["sha256"] == before
    gate.set()
    status = finished(session, done["correction_id"])
    assert status["state"] == "done" and status["result"]["frames"] == 5, status
    expected = streamed(store, shelf[:5]).digest()["sha256"]
    assert session.digest()["sha256"] == expected
    again = reopened(store, tmp_path)
    try:
        assert again.get(session.id).digest()["sha256"] == expected
    finally:
        again.close()


def test_a_correction_in_place_is_one_step_for_renders_exports_and_digests(tmp_path, shelf, monkeypatch):
    """A correction of recent frames rolls the served scene back and re-folds them in place: a reader
    that comes in between (a render's or an export's decode, a digest) waits for the step and sees the
    corrected scene, never the rolled-back one or a part of the re-fold (an export of a scene that
    never existed)."""
    from canonical_core.scene import Scene, refold

    store = SessionStore(tmp_path, 8)
    store.open()
    session = streamed(store, shelf[:5])
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    seen, readers = [], []

    def reader_first(fold):  # ``fold`` with a reader started before the correction's first fold
        def folded(*args):
            if not readers:  # the scene is rolled back now
                reader = threading.Thread(target=lambda: seen.append((session.scene.digest(),
                                                                       len(session.scene.gaussians(colours="last")))))
                readers.append(reader)
                reader.start()
                reader.join(0.5)
            return fold(*args)
        return folded

    monkeypatch.setattr(Scene, "fold", reader_first(Scene.fold))  # between a rollback and a fold
    monkeypatch.setattr(refold, "fold_kept", reader_first(refold.fold_kept))  # within one step
    assert session.corrections.correct({shelf[4]["frame_id"]: shift @ shelf[4]["c2w"]})["frames"] == 5
    readers[0].join(60)
    monkeypatch.undo()
    corrected = streamed(store, shelf[:5], {4: shift @ shelf[4]["c2w"]})
    assert seen == [(corrected.scene.digest(), len(corrected.scene.gaussians(colours="last")))]
    store.close()


def test_the_session_list_never_shows_a_correction_rolled_back(tmp_path, shelf, monkeypatch):
    """While a correction of recent frames folds them again (the scene rolled back, under the lock),
    what is read without the lock (the session list, the service's totals) shows the counts it
    was answered with before, not the rolled-back scene's; afterwards, the corrected scene's."""
    from canonical_core.scene import refold

    store = SessionStore(tmp_path, 8)
    store.open()
    session = streamed(store, shelf[:5])
    before = (5, len(session.scene))
    seen = []

    def looked(*args):  # the scene is rolled back, or part re-folded, here
        seen.append(((session.scene.frames, len(session.scene)), (session.summary()["frames"], session.summary()["voxels"]),
                     (store.totals()["frames"], store.totals()["voxels"])))
        return fold_kept(*args)

    fold_kept = refold.fold_kept
    monkeypatch.setattr(refold, "fold_kept", looked)
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    session.corrections.correct({shelf[3]["frame_id"]: shift @ shelf[3]["c2w"]})
    monkeypatch.undo()
    assert len(seen) == 2 and seen[0][0][0] == 3  # rolled back to 3 frames, then 3 and 4 folded again
    assert all(listed == totals == before for _, listed, totals in seen), (before, seen)
    assert session.summary()["frames"] == 5 and session.summary()["voxels"] == len(session.scene)
    store.close()


def test_frames_acknowledged_before_the_archive_caught_up_are_archived_at_restart(tmp_path, shelf):
    """A kill -9 after frames were acknowledged (in the fsynced log) but before the archive's writer
    wrote them: the restart archives them from the log, and a correction then reaches them."""
    store = SessionStore(tmp_path, 8)
    store.open()
    session = streamed(store, shelf[:5], snapshot_every=3)  # a snapshot after 3 frames: the log holds 3 and 4
    session.archive.flush()
    archive = session.path / ARCHIVE
    cut = session.archive._records[3][0]  # the offset of frame 3's record: frames 3 and 4 never written
    archive.write_bytes(archive.read_bytes()[:cut])
    again = reopened(store, tmp_path)
    try:
        restored = again.get(session.id)
        assert restored.archive.problem is None and len(restored.archive.entries) == 5
        shift = np.eye(4)
        shift[:3, 3] = [0.01, 0.0, 0.0]
        restored.corrections.correct({shelf[3]["frame_id"]: shift @ shelf[3]["c2w"]})
        expected = streamed(again, shelf[:5], {3: shift @ shelf[3]["c2w"]})
        assert restored.digest()["sha256"] == expected.digest()["sha256"]
    finally:
        again.close()


def test_the_services_undo_setting_reaches_its_sessions_and_their_memory(tmp_path, shelf):
    from server.app import create_app
    from server.settings import Settings

    memory, undo = {}, {}
    for depth in (0, 7):
        store = create_app(Settings(data_dir=tmp_path / str(depth), correction_undo_frames=depth)).state.store
        store.open()
        try:
            session = streamed(store, shelf[:3])
            assert session.undo_depth == depth and session.scene._undo.depth == depth
            memory[depth], undo[depth] = session.scene.memory_bytes(), session.scene.undo_bytes()
            # bounded by a share of the map as well: the shelf's frames each touch much of it
            assert session.scene._undo.max_share == MAX_UNDO_SHARE
            assert undo[depth] <= MAX_UNDO_SHARE * session.scene._voxels.nbytes() or len(session.scene._undo) <= MIN_KEPT
        finally:
            store.close()
    assert undo[0] == 0 and undo[7] > 0
    assert memory[7] == memory[0] + undo[7]  # the records count in the session's memory


@pytest.mark.parametrize("undo_depth", [0, session_module.UNDO_DEPTH])  # a new scene re-folded, or rolled back in place
def test_a_correction_carries_the_colour_solution_to_the_corrected_scene(tmp_path, shelf, monkeypatch, undo_depth):
    monkeypatch.setattr(session_module, "UNDO_DEPTH", undo_depth)
    store = SessionStore(tmp_path, 8)
    store.open()
    try:
        session = store.create(SceneConfig(voxel_size=0.01, colour_solve={"views": 3, "scale": 1.0}))
        for kwargs in shelf[:5]:
            session.add_frame(*payload(kwargs), 1000, 3600)
        assert session.solve_colours()  # as the service's background solve does
        solved = session.scene._decoding.solution
        offsets_of = dict(zip(session.scene._voxels.state["keys"][solved.rows].tolist(), solved.offsets))
        shift = np.zeros((4, 4))
        shift[:3, 3] = 0.01
        session.corrections.correct({shelf[4]["frame_id"]: shelf[4]["c2w"] + shift})
        carried = session.scene._decoding.solution  # the served scene shows it until its re-solve lands
        assert carried is not None and session.scene.frames - carried.frames >= session.config.colour_solve.refresh
        assert session.colour_solve_due()
        keys = session.scene._voxels.state["keys"][carried.rows].tolist()
        assert len(keys) > 0.8 * len(solved.rows)
        assert all(np.array_equal(offset, offsets_of[key]) for key, offset in zip(keys, carried.offsets))
    finally:
        store.close()


def test_a_correction_while_a_snapshot_is_written_drops_that_snapshot(tmp_path, shelf, monkeypatch):
    """A snapshot written off the acknowledged path holds frames that a correction then changes: it
    is never committed (its file is removed), and the files restore the corrected scene."""
    written, release = hold_snapshot_commits(monkeypatch)
    store = SessionStore(tmp_path, 8)
    store.open()
    shift = np.eye(4)
    shift[:3, 3] = [0.01, 0.0, 0.0]
    session = store.create(CONFIG)
    for kw in shelf:  # a snapshot due at 6 frames, held while the seventh folds
        session.add_frame(*payload(kw, shift @ kw["c2w"]), 6, 3600)
    assert written.wait(60) and session.snapshots.frames == 0
    pending = session.snapshots.pending
    session.corrections.correct({kw["frame_id"]: kw["c2w"] for kw in shelf[4:]})  # frames 4 and 5 are in that snapshot
    release.set()
    pending.writer.join(60)
    assert session.snapshots.frames == 0 and not list(session.path.glob("scene.snap*"))
    expected = [kw if k >= 4 else {**kw, "c2w": shift @ kw["c2w"]} for k, kw in enumerate(shelf)]
    digest = streamed(store, expected).digest()["sha256"]
    assert session.digest()["sha256"] == digest
    again = reopened(store, tmp_path)  # the files as a kill -9 now leaves them
    try:
        assert again.get(session.id).digest()["sha256"] == digest
    finally:
        again.close()


def test_sessions_commit_the_preallocated_memory_when_made_corrected_and_restored(tmp_path, shelf, monkeypatch):
    monkeypatch.setattr(session_module, "UNDO_DEPTH", 0)  # no roll-back in place: a correction re-folds a new scene
    rows, row_bytes = 50_000, 120  # a row of the state is about 150 bytes
    store = SessionStore(tmp_path, 8)
    store.preallocate_voxels = rows
    store.open()
    plain = SessionStore(tmp_path / "plain", 8)
    plain.open()
    try:
        session, twin = streamed(store, shelf[:3]), streamed(plain, shelf[:3])
        assert len(session.scene) < rows and session.scene.digest() == twin.scene.digest()  # the same scene
        assert session.scene.memory_bytes() >= twin.scene.memory_bytes() + (rows - len(twin.scene)) * row_bytes
        served = session.scene
        session.corrections.correct({shelf[0]["frame_id"]: shelf[0]["c2w"]})  # frame 0: a full re-fold into a new scene
        assert session.scene is not served and session.scene.memory_bytes() >= rows * row_bytes
        capped = store.create(SceneConfig(voxel_size=0.01, max_voxels=1_000))  # at most its own cap, no error
        assert capped.scene.memory_bytes() < rows * row_bytes
        again = reopened(store, tmp_path, preallocate_voxels=rows)  # a restart after kill -9, the same setting
        try:
            restored = again.get(session.id)
            assert restored.scene.digest() == session.scene.digest()
            assert restored.scene.memory_bytes() >= rows * row_bytes
        finally:
            again.close()
    finally:
        plain.close()
        store.close()


def test_a_background_correction_a_restart_cannot_make_is_undone_and_the_session_served(tmp_path, shelf):
    """A kill -9 after a background correction was archived and before its re-fold ended: the restart
    re-folds it, and where that fails (a pose past the voxel cap) it undoes it as the job would have:
    the session is served as it was, not left unloadable, and the correction's status says failed."""
    from canonical_core import Scene

    far = shelf[0]["c2w"].copy()
    far[:3, 3] += 3.0
    moved = Scene(CONFIG)
    for k, kwargs in enumerate(shelf[:4]):
        moved.fold(payload(kwargs, far if k == 0 else None)[1])
    store = SessionStore(tmp_path, 8)
    store.open()
    plain = len(streamed(store, shelf[:4]).scene)
    assert len(moved) > plain + 100  # the move makes the scene larger than the cap below lets it be
    session = store.create(SceneConfig(voxel_size=0.01, max_voxels=(plain + len(moved)) // 2))
    for kwargs in shelf[:4]:
        session.add_frame(*payload(kwargs), 1000, 3600)
    before = session.digest()["sha256"]
    session.archive.flush()
    session.archive.append_correction({session.archive.entries[0].arrival: far}, [], 0, "job1",
                                      {"corrected": 1, "removed": 0, "dropped": 0, "frames_before": 4})
    for _ in range(2):  # the restart undoes it; the next reads the undo
        store = reopened(store, tmp_path)
        again = store.get(session.id)
        assert again.digest()["sha256"] == before and again.scene.frames == 4
        status = again.corrections.status("job1")
        assert status["state"] == "failed" and "max_voxels" in status["error"]
    store.close()
