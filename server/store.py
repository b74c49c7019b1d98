"""The session store: sessions on disk and their locks. No HTTP here.

Layout: ``<data_dir>/.lock`` (held by the one server that uses the directory), and one folder per
session under ``<data_dir>/sessions/<id>/``:

- ``meta.json``: id, creation time and the SceneConfig, written once, atomically.
- ``frames.log``: the append-only frame log (`server.framelog`). A frame is appended and fsynced
  before it is acknowledged; the append runs on a writer thread while the frame folds (the fsync is
  a wait on the disk, the fold is compute), and the acknowledgement waits for both. An append that
  fails (a full disk) is cut off at once and the fold is undone (the scene rolled back, or rebuilt
  from disk); a record whose fold fails is cut off again. A render in that moment may show a frame
  that is not yet acknowledged; it never loses one that is. On start a torn tail (a crash
  mid-append: never acknowledged) is cut off; damage anywhere else is never cut: the log is copied to
  ``quarantine/`` and the session is not served until ``canonical repair`` decides.
- ``scene.snap``: `Scene.to_bytes` snapshot (atomic), holding ``scene.frames`` frames. Due every
  ``snapshot_every_frames`` frames or ``snapshot_every_seconds``, and written on shutdown; after it
  the log is replaced by one checkpoint record (the frames the snapshot holds and the frame-id
  table) and the records of the frames after them. A due snapshot is written off the acknowledged
  path: the frame that makes it due copies the state (`Scene.snapshot_parts`) and is answered; a
  writer thread encodes it into ``scene.snap.<n>.next`` (fsynced) and then, under the session's
  lock, renames it to ``scene.snap`` and restarts the log. A crash before that rename leaves the
  previous snapshot and the whole log (the ``.next`` file is removed on start).
  Restart = load snapshot, replay records whose index >= the snapshot's frame count. Folding is
  deterministic, so the replayed scene equals the uninterrupted one bit for bit. A snapshot that
  cannot be written is not an error of the request that triggered it: that frame is already durable
  in the log; the failure shows in the session's stats and in /metrics.

A session whose files do not add up on start (damaged log, a log or snapshot removed by hand, an
unreadable snapshot, a missing meta.json) is listed as unavailable with the reason, and its requests
get that reason; its files are left as they are.

Locks: ``Session.lock`` serialises what reads or writes one session's scene and files (fold,
snapshot, digest); rendering works on decoded Gaussians outside it, so a render never sees a
half-folded scene and never blocks another session. Decoded Gaussians come from `Scene.gaussians`,
which decodes once per change and holds the scene's own lock only to copy its sums, so folds go on
while a decode (and its colour solve) runs.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import secrets
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, NamedTuple

import msgpack
import numba

from canonical_core import Frame, Gaussians, SceneConfig
from canonical_core.scene import FoldReport, Scene
from canonical_core.scene.scene import DEFAULT_UNDO_DEPTH
from canonical_core.scene.corrections import check_poses, corrected_stream, resolve_frames

from . import wire
from .archive import ARCHIVE, RETENTIONS, Retention, SessionArchive, archive_failure, names_payload, payload_digest
from .framelog import (FrameLog, LogWedged, RepairAction, StorageError, encode, fsync_dir, repaired, scan,
                       write_atomic)

log = logging.getLogger("canonical.store")

# the frame log's appends (digest, write, fsync) run here while their frames fold: one writer per job
# that can fold at a time is enough (a session's appends are ordered by its lock)
LOG_WRITERS = ThreadPoolExecutor(max_workers=8, thread_name_prefix="frame-log")


class ColourSolves(ThreadPoolExecutor):
    """The colour re-solves of sessions that keep views (`SceneConfig.colour_solve.refresh`): they run
    here, not in the render that found one due, which shows the last solution. One at a time: each
    is seconds of work on every core, and folds and renders share those cores. A re-solve that
    fails is logged (the next render that finds one due starts another)."""

    def __init__(self):
        super().__init__(max_workers=1, thread_name_prefix="colour-solve")

    def submit(self, fn, /, *args, **kwargs):
        future = super().submit(fn, *args, **kwargs)
        future.add_done_callback(_log_failure)
        return future


def _log_failure(future) -> None:
    if future.exception() is not None:
        log.error("colour re-solve failed", exc_info=future.exception())


COLOUR_SOLVES = ColourSolves()

META, LOG, SNAPSHOT, QUARANTINE, LOCK = "meta.json", "frames.log", "scene.snap", "quarantine", ".lock"
BASE, BASE_META = "base.snap", "base.json"  # a corrected stream's state at a frame count before its end
BASE_EVERY = 25  # a correction keeps the state at the last multiple of this below its frame count
UNDO_DEPTH = DEFAULT_UNDO_DEPTH  # folds an archived session's scene can roll back in place (`Scene.rollback`)
BACKGROUND_FRAMES = 64  # default: a correction that would re-fold more frames re-folds in the background
TOMBSTONE = ".deleted-"
SNAPSHOT_RETRY_SECONDS = 30.0  # after a failed snapshot, folds do not try again sooner (each try writes it all)
PENDING_SNAPSHOT = "scene.snap.{}.next"  # a snapshot written off the acknowledged path, not yet committed


class SessionNotFound(KeyError):
    def __init__(self, session_id: str):
        super().__init__(session_id)
        self.session_id = session_id


class TooManySessions(RuntimeError):
    pass


class SessionUnavailable(RuntimeError):
    """A session whose files do not add up (or whose log cannot be written): not served, with the reason."""

    def __init__(self, session_id: str, reason: str, retry_later: bool = False):
        super().__init__(f"session {session_id}: {reason}")
        self.session_id, self.reason, self.retry_later = session_id, reason, retry_later


class FrameIdConflict(ValueError):
    """A frame_id that the session already folded, sent again with other content."""


class CorrectionRefused(ValueError):
    """A correction the session cannot take (no archive, or one that cannot serve it): 409 naming ``field``."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class DataDirLocked(RuntimeError):
    """Another process serves the data directory."""


class Unrestorable(RuntimeError):
    """The files of a session do not add up; the message says how, and what ``canonical repair`` can do."""


def configure_thread(threads: int | None) -> None:
    """Apply the ``threads`` setting in the calling thread (numba's count is per thread)."""
    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


# -- sessions ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FoldedFrame:
    """What the session remembers of a frame that carried a frame_id: enough to answer its retry."""

    index: int
    digest: str  # of its log record's payload
    # the fold report it got; None where a crash between a snapshot and the log's restart left only
    # the frame's record (its report is then not known: the retry gets zero counts)
    report: dict | None


@dataclass
class CorrectionJob:
    """A correction re-folding in the background (`Session.correct`), as its status reports it."""

    id: str
    total: int  # frames to re-fold (grows with the frames that arrive meanwhile)
    state: str = "pending"  # pending, running, done, failed
    refolded: int = 0
    error: str | None = None
    result: dict | None = None

    def status(self) -> dict:
        return {"correction_id": self.id, "state": self.state, "refolded": self.refolded, "total": self.total,
                "error": self.error, "result": self.result}


class Restored(NamedTuple):
    scene: Scene
    log: FrameLog
    snapshot_frames: int
    frame_ids: dict[str, FoldedFrame]


@dataclass(eq=False)
class PendingSnapshot:
    """A snapshot of a session's first ``frames`` frames, being written off the acknowledged path."""

    number: int  # names its file (`PENDING_SNAPSHOT`): one writer per file
    frames: int
    log_offset: int  # where the log's records of the frames after it begin
    checkpoint: bytes  # the payload of the log's checkpoint record once it is committed
    captured: float  # monotonic time of the capture
    cancelled: bool = False  # the session's files changed otherwise meanwhile: never commit it
    writer: threading.Thread | None = None


@dataclass(eq=False)
class Session:
    id: str
    path: Path
    config: SceneConfig
    created: float
    scene: Scene
    log: FrameLog
    snapshot_frames: int
    frame_ids: dict[str, FoldedFrame] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    deleted: bool = False
    wedged: str | None = None  # why the log cannot take appends until a restart (its tail is unknown)
    dirty_since: float | None = None  # when the oldest frame not in the snapshot was folded
    snapshot_error: str | None = None  # why the last snapshot failed (frames stay durable in the log)
    snapshot_failures: int = 0
    snapshot_retry_at: float = 0.0  # monotonic time before which a fold does not retry a failed snapshot
    archive: SessionArchive | None = None  # the kept frames (None: retention "none")
    version: int = 0  # bumped by every fold and correction: a correction computed on an older one is refused
    background: CorrectionJob | None = None  # the correction re-folding in the background, if one is
    background_frames: int = BACKGROUND_FRAMES  # re-folds longer than this run in the background
    undo_depth: int = field(default_factory=lambda: UNDO_DEPTH)  # folds its scene can roll back in place
    preallocate_voxels: int = 0  # voxels whose memory its scenes commit up front (`Scene.preallocate`)
    jobs: dict[str, CorrectionJob] = field(default_factory=dict)  # background corrections since the start
    pending_snapshot: PendingSnapshot | None = None  # the snapshot being written off the acknowledged path
    snapshots_started: int = 0  # numbers the pending snapshots' files
    background_snapshots: ClassVar[bool] = True  # due snapshots are written off the acknowledged path

    def __post_init__(self):
        self._prepare_scene()

    def _prepare_scene(self) -> None:
        """The served scene's settings that its snapshot does not keep. Sessions that can be
        corrected keep undo records of their last folds: a correction of recent frames then rolls the
        served scene back and re-folds only them (`correct`). And the scene commits the memory of
        `preallocate_voxels` voxels up front."""
        if self.archive is not None:
            self.scene.keep_undo(self.undo_depth)
        self._preallocate(self.scene)

    def _preallocate(self, scene: Scene) -> None:
        """`Scene.preallocate` of `preallocate_voxels` voxels, at most the session's ``max_voxels``."""
        scene.preallocate(min(self.preallocate_voxels, self.config.max_voxels or self.preallocate_voxels))

    # -- writing (callers hold no lock; these take it) ------------------------------------------
    def add_frame(self, payload: bytes, frame: Frame, snapshot_every_frames: int,
                  snapshot_every_seconds: float) -> tuple[FoldReport, bool]:
        """Log (fsynced), fold, maybe snapshot; returns the fold report and whether it is a replay.

        A frame whose ``frame_id`` the session already folded is not folded again: its first report
        comes back (replay = True), or `FrameIdConflict` if its content differs. The record is logged
        on a writer thread while the frame folds, and the report is returned once both are done. A
        frame that cannot be made durable raises `StorageError`, its fold undone. On a ValueError the
        log record is cut off again and the scene is unchanged (the library validates before it mutates)."""
        with self.lock:
            self._check_alive()
            known = self.frame_ids.get(frame.frame_id) if frame.frame_id is not None else None
            if known is not None:
                if not names_payload(known.digest, payload):
                    raise FrameIdConflict(f"frame_id: {frame.frame_id!r} was folded as frame {known.index} with other content")
                report = known.report or {"frame_index": known.index, "observations": 0, "new_voxels": 0,
                                          "updated_voxels": 0, "representative_switches": 0, "ms": 0.0}
                return FoldReport(**report), True
            if self.wedged:
                raise SessionUnavailable(self.id, self.wedged, retry_later=True)
            frames = self.scene.frames
            logged = LOG_WRITERS.submit(lambda: (payload_digest(payload), self.log.append(frames, payload)))
            try:
                report = self.scene.fold(frame)
            except Exception as exc:
                self._fold_failed(logged, exc)
                raise
            try:
                digest, _ = logged.result()
            except StorageError as exc:
                self._append_failed(exc, frames)
                raise
            self._archive_frame(frame.frame_id, digest, payload)
            if frame.frame_id is not None:
                self.frame_ids[frame.frame_id] = FoldedFrame(report.frame_index, digest, report.to_dict())
            self.version += 1
            now = time.monotonic()
            self.dirty_since = self.dirty_since or now
            if now >= self.snapshot_retry_at and (self.scene.frames - self.snapshot_frames >= snapshot_every_frames
                                                  or now - self.dirty_since >= snapshot_every_seconds):
                self._snapshot_soon()
            return report, False

    def _fold_failed(self, logged, exc: Exception) -> None:
        """A fold raised while its record was being logged: the record is cut off again once written.
        A ValueError left the scene unchanged (the library validates before it mutates); anything else
        may have left it half-folded, so it is rebuilt from disk (without this frame)."""
        try:
            _, offset = logged.result()
        except StorageError as storage:
            self._note_wedged(storage)
        else:
            self.log.truncate(offset)
        if not isinstance(exc, ValueError):
            self._recover(None, "a failed fold")

    def _append_failed(self, exc: StorageError, frames: int) -> None:
        """The frame folded but its record is not durable (cut off, the log wedged, or the session
        fenced by another owner): the fold is undone."""
        self._note_wedged(exc)
        self._recover(frames, "a fold whose frame was not logged")

    def _recover(self, frames: int | None, after: str) -> None:
        """The scene back to its first ``frames`` frames by its undo records where they reach back
        (None: not by them), else rebuilt from disk; a session that cannot be is no longer served."""
        try:
            if frames is not None and self.scene.undo_floor <= frames:
                self.scene.rollback(frames)
            else:
                self._reload()
        except Exception:
            log.exception("session %s: cannot be rebuilt after %s; no longer serving it", self.id, after)
            self.deleted = True

    def _note_wedged(self, exc: StorageError) -> None:
        if isinstance(exc, LogWedged):
            self.wedged = f"{exc.strerror}; restart the service once the storage is fixed"
            log.error("session %s: %s", self.id, self.wedged)

    def _archive_frame(self, frame_id: str | None, digest: str, payload: bytes) -> None:
        """Archive a folded frame: off the acknowledged path (the log holds it durably until the
        archive does), but at once while a background correction re-folds, which catches up on the
        archive's frames. A failure leaves the frame in the log and corrections refused until a restart
        archives it from there."""
        archive = self.archive
        if archive is None or archive.problem is not None:
            return
        if self.background is None:
            archive.defer_frame(frame_id, digest, payload)
            return
        archive.flush()
        try:
            archive.append_frame(frame_id, digest, payload)
        except Exception as exc:  # noqa: BLE001 - the frame is folded and in the log; a restart archives it
            archive.problem = archive_failure(exc)

    def snapshot(self, background: bool = False) -> None:
        """Snapshot the session if it has frames its snapshot lacks: now, or with ``background`` off the
        caller's path (`_snapshot_soon`)."""
        with self.lock:
            if not self.deleted and self.scene.frames != self.snapshot_frames:
                self._snapshot_soon() if background else self._snapshot()

    def _snapshot(self) -> None:
        """Snapshot, then start the log afresh with a checkpoint. A failure is recorded, not raised: every
        frame is durable in the log already, and the next due snapshot tries again. None while a
        correction re-folds in the background: its swap snapshots (the saved states it starts from
        stay as they are, and a restart before it re-folds from the archive)."""
        if self.background is not None:
            return
        self._cancel_pending_snapshot()
        try:
            write_atomic(self.path / SNAPSHOT, self.scene.to_bytes())
        except OSError as exc:
            self._snapshot_failed(exc)
            return
        self.snapshot_frames, self.dirty_since, self.snapshot_error = self.scene.frames, None, None
        self._restart_log(self.snapshot_frames, checkpoint_payload(self.frame_ids, self._corrections()), b"")

    def _snapshot_failed(self, exc: Exception) -> None:
        self.snapshot_error = f"{SNAPSHOT}: {getattr(exc, 'strerror', None) or exc}"
        self.snapshot_failures += 1
        self.snapshot_retry_at = time.monotonic() + SNAPSHOT_RETRY_SECONDS
        log.error("session %s: snapshot failed (%s); its frames stay in the log", self.id, self.snapshot_error)

    def _restart_log(self, frames: int, checkpoint: bytes, tail: bytes) -> None:
        """The log replaced by a checkpoint of the snapshot's ``frames`` and ``tail`` (the records of
        the frames after them), once the archive holds every frame."""
        if self.archive is not None:
            self.archive.flush()  # the log is restarted below: the archive must hold its frames first
            if self.archive.problem is not None:
                return  # the log keeps the frames the archive may lack: a restart archives them from it
        try:
            self.log.reset([encode(frames, checkpoint, checkpoint=True), tail])
        except OSError as exc:  # the old records stay; a restart skips those the snapshot holds
            log.error("session %s: the log could not be restarted after a snapshot (%s)", self.id, exc.strerror or exc)

    def _snapshot_soon(self) -> None:
        """A due snapshot, off the acknowledged path (the caller holds the lock). Here the state is
        copied (`Scene.snapshot_parts`: the sums, a memory copy); a writer thread encodes it and writes
        it to its own file (fsynced), then, under the lock, commits it: the file becomes the snapshot
        and the log keeps only the records after it. The frames folded meanwhile stay in the log; a
        crash before the commit restarts from the previous snapshot and the whole log. One at a time."""
        if not self.background_snapshots:
            self._snapshot()
            return
        if self.pending_snapshot is not None or self.background is not None:
            return
        parts = self.scene.snapshot_parts()
        self.snapshots_started += 1
        pending = PendingSnapshot(self.snapshots_started, self.scene.frames, self.log.size(),
                                  checkpoint_payload(self.frame_ids, self._corrections()), time.monotonic())
        self.pending_snapshot = pending
        pending.writer = threading.Thread(target=self._write_pending_snapshot, args=(pending, parts), daemon=True,
                                          name=f"snapshot-{self.id[:8]}")
        pending.writer.start()

    def wait_for_snapshot(self, timeout: float | None = None) -> None:
        """Wait until the snapshot being written, if any, is committed or dropped (not with the lock held:
        its writer takes it to commit)."""
        pending = self.pending_snapshot
        if pending is not None and pending.writer is not None:
            pending.writer.join(timeout)

    def _write_pending_snapshot(self, pending: PendingSnapshot, parts: tuple[dict, dict]) -> None:
        path = self.path / PENDING_SNAPSHOT.format(pending.number)
        try:  # encoded straight into the file: no second copy of the state in memory
            write_atomic(path, lambda f: Scene.encode_snapshot(*parts, out=f))
            error = None
        except Exception as exc:  # noqa: BLE001 - recorded like a failed snapshot; the frames stay in the log
            error = exc
        del parts
        with self.lock:
            if self.pending_snapshot is pending:
                self.pending_snapshot = None
            if pending.cancelled or self.deleted or error is not None:
                _remove_quietly(path)
                if error is not None and not pending.cancelled and not self.deleted:
                    self._snapshot_failed(error)
                return
            try:
                os.replace(path, self.path / SNAPSHOT)
                fsync_dir(self.path)
            except OSError as exc:
                _remove_quietly(path)
                self._snapshot_failed(exc)
                return
            self.snapshot_frames, self.snapshot_error = pending.frames, None
            self.dirty_since = None if self.scene.frames == pending.frames else pending.captured
            self.version += 1  # a correction computed from the snapshot before this one is refused
            try:
                with open(self.log.path, "rb") as f:  # the records of the frames folded meanwhile
                    f.seek(pending.log_offset)
                    tail = f.read()
            except OSError as exc:  # the old records stay; a restart skips those the snapshot holds
                log.error("session %s: the log could not be read after a snapshot (%s)", self.id, exc.strerror or exc)
                return
            self._restart_log(pending.frames, pending.checkpoint, tail)

    def _cancel_pending_snapshot(self) -> None:
        """The session's files are about to change otherwise (a snapshot now, a correction, a reload):
        the snapshot being written is never committed (its writer removes its file)."""
        if self.pending_snapshot is not None:
            self.pending_snapshot.cancelled = True
            self.pending_snapshot = None

    def _reload(self) -> None:
        self._cancel_pending_snapshot()
        self.log.close()
        self.scene, self.log, self.snapshot_frames, self.frame_ids = restore_scene(self.path, self.config)
        self._prepare_scene()

    def _corrections(self) -> int:
        """Archived corrections the served scene holds (not one still re-folding in the background)."""
        if self.archive is None:
            return 0
        return self.archive.corrections - (self.background is not None)

    # -- corrections ------------------------------------------------------------------------------
    def correct(self, poses: dict | None = None, remove: list | None = None, wait: bool = True) -> dict:
        """Give archived frames new poses (``{frame key: c2w}``) and/or remove frames (keys as in
        `corrections.resolve_frames`), as one durable step; returns what it did.

        The corrected scene is the re-fold of the archived frames, in order, with the corrections
        applied (`Scene.refolded`): equal to a session that was streamed the corrected frames.

        A correction whose frames are among the scene's last folds (``undo_depth``) rolls the served
        scene back and re-folds them under the session's lock (`Scene.rollback`): about k folds for
        the k most recent frames. Any other is computed outside the lock from the latest saved state
        before its first frame, so the old scene is served meanwhile; a fold or another correction
        that lands in the meantime makes it `CorrectionRefused` (409), nothing changed.

        The correction is archived (fsynced) before the scene is swapped and acknowledged. Then the
        files catch up: where the correction leaves the snapshot's frames as they were, the log is
        rewritten with the corrected frames after them; otherwise the scene is snapshotted and the
        log restarted. A restart between the two re-folds from the archive (`restore_session`). Bad
        keys or poses raise ValueError naming ``poses.<key>`` or ``frames.<key>``, nothing changed.

        A correction that would re-fold more than ``background_frames`` frames, or any with ``wait``
        False, is archived and answered at once (``state`` "pending", a ``correction_id``), and
        re-folds in the background (`_refold_in_background`); the old scene is served and takes
        frames meanwhile. Another correction that arrives then is `CorrectionRefused` (409)."""
        with self.lock:
            self._check_alive()
            archive = self._usable_archive()
            if self.wedged:
                raise SessionUnavailable(self.id, self.wedged, retry_later=True)
            self._check_no_background()
            self._cancel_pending_snapshot()  # the correction rewrites the files: a snapshot of before must not land after
            refs, entries, version = archive.refs(), list(archive.entries), self.version
            changed = check_poses(poses, refs) if poses else {}
            removed = set(resolve_frames(remove or [], refs, "frames"))
            if not changed and not removed:
                raise ValueError("poses: names no frame")
            dropped = {k for k, e in enumerate(entries) if not e.kept} - removed  # retention "keyframes"
            first = min(set(changed) | removed | dropped)
            done = {"id": self.id, "corrected": len(set(changed) - removed), "removed": len(removed),
                    "dropped": len(dropped), "frames_before": self.scene.frames, "state": "done", "correction_id": None}
            short = len(entries) - first <= self.background_frames
            if wait and short and first >= self.scene.undo_floor and all(e.kept for e in entries[first:]):
                self._correct_in_place(archive, entries, changed, removed | dropped, first)
                return {**done, "frames": self.scene.frames}
            bases = self._bases(archive, first)
            appearance = self.scene.appearance
            start = bases[0][0] if bases else 0
            # retention "keyframes" re-folds in the request: a frame it does not keep cannot be caught up on
            if archive.retention == "all" and (not wait or len(entries) - start > self.background_frames):
                job = CorrectionJob(secrets.token_hex(8), len(entries) - len(removed | dropped) - start)
                self._commit_correction(archive, entries, changed, removed | dropped, first, job.id)
                self.background = self.jobs[job.id] = job
                answer = {**done, "frames": self.scene.frames, "state": job.state, "correction_id": job.id}
                threading.Thread(target=self._refold_in_background, args=(job, archive, bases, appearance, done),
                                 name=f"correction-{job.id}", daemon=True).start()
                return answer
        scene, checkpoints = self._refolded(archive, entries, changed, removed | dropped, appearance, bases)
        with self.lock:
            self._check_alive()
            if self.version != version:
                raise CorrectionRefused("session_id", "a frame or another correction reached the session while this "
                                                      "correction was computed; send it again")
            self._commit_correction(archive, entries, changed, removed | dropped, first)
            scene.carry_colour_solution(self.scene)
            self.scene = scene
            self._persist_correction()
            self._keep_base(checkpoints)
            return {**done, "frames": scene.frames}

    def _commit_correction(self, archive: SessionArchive, entries: list, changed: dict, removed: set,
                           first: int, job: str | None = None) -> None:
        """Archive the correction (fsynced: the commit point), and what follows from it in memory (for a
        background correction ``job``, at its swap)."""
        archive.append_correction({entries[k].arrival: c2w for k, c2w in changed.items()},
                                  [entries[k].arrival for k in removed], first, job)
        self.version += 1
        if job is None:
            self.frame_ids = archived_frame_ids(archive, self.frame_ids)

    def _check_no_background(self) -> None:
        job = self.background
        if job is not None:
            raise CorrectionRefused("session_id", f"correction {job.id} is still re-folding in the background "
                                                  f"({job.refolded} of {job.total} frames); send this one when its "
                                                  "status (GET .../corrections/{id}) says done")

    def _refold_in_background(self, job: CorrectionJob, archive: SessionArchive, bases: list[tuple[int, Path]],
                              appearance, done: dict) -> None:
        """Re-fold the archived (corrected) stream from the latest valid saved state, then catch up on
        the frames that arrived meanwhile, in arrival order, and swap the scene in under the lock once
        none is left: the result equals the corrected stream folded afresh. A failure leaves the old
        scene served and the session read-only (the archive holds the correction: a restart retries)."""
        job.state = "running"
        try:
            with self.lock:
                entries = list(archive.entries)
            scene, checkpoints = self._refolded(archive, entries, {}, set(), appearance, bases, job)
            while True:
                with self.lock:
                    self._check_alive()
                    arrived = archive.entries[len(entries):]
                    if not arrived:
                        self._swap_in(scene, checkpoints, archive)
                        job.result = {**done, "frames": scene.frames, "state": "done", "correction_id": job.id}
                        job.state, self.background = "done", None
                        return
                    job.total += len(arrived)
                for frame in archive.frames(arrived):
                    scene.fold(frame)
                    job.refolded += 1
                entries += arrived
        except Exception as exc:  # noqa: BLE001 - recorded in the status and the session's state
            log.exception("session %s: background correction %s failed", self.id, job.id)
            with self.lock:
                job.state, job.error, self.background = "failed", f"{type(exc).__name__}: {exc}", None
                self.wedged = (f"correction {job.id} failed while re-folding ({job.error}); it is in the archive, "
                               "so a restart retries it")

    def _swap_in(self, scene: Scene, checkpoints: dict[int, bytes], archive: SessionArchive) -> None:
        """The background re-fold's scene becomes the served one (the caller holds the lock)."""
        scene.carry_colour_solution(self.scene)
        self.scene, self.version = scene, self.version + 1
        self.frame_ids = archived_frame_ids(archive, self.frame_ids)
        self.background = None
        self._persist_correction()
        self._keep_base(checkpoints)

    def correction_status(self, correction_id: str) -> dict:
        """The status of a background correction; one this process did not start but the archive holds
        was finished by the restart that replayed it. Raises KeyError for an unknown id."""
        job = self.jobs.get(correction_id)
        if job is not None:
            return job.status()
        if self.archive is not None and correction_id in self.archive.correction_ids:
            return {"correction_id": correction_id, "state": "done", "refolded": 0, "total": 0, "error": None,
                    "result": None}
        raise KeyError(correction_id)

    def _correct_in_place(self, archive: SessionArchive, entries: list, changed: dict, removed: set,
                          first: int) -> None:
        """`correct` for frames among the last folds, under the session's lock: roll the scene back to
        ``first`` frames, fold the corrected frames after it, then archive the correction. If a fold
        or the archive write fails, the scene is rolled back again and the old frames re-folded (they
        folded before), and the error is raised: nothing changed."""
        scene = self.scene

        def fold_from_first(frames) -> None:
            scene.rollback(first)
            for frame in frames:
                scene.fold(frame)

        tail = entries[first:]
        try:
            fold_from_first(corrected_stream(archive.frames(tail), {k - first: c2w for k, c2w in changed.items()},
                                             {k - first for k in removed}))
            self._commit_correction(archive, entries, changed, removed, first)
        except BaseException:
            fold_from_first(list(archive.frames(tail)))
            raise
        if first >= self.snapshot_frames:
            self._rewrite_log(archive, first)
        else:
            self._persist_correction()

    def _rewrite_log(self, archive: SessionArchive, first: int) -> None:
        """After a correction whose first frame ``first`` comes after the snapshot's: the log's records
        from that frame on are cut off, the corrected frames appended, then a checkpoint counting the
        archive's corrections, so a restart (snapshot + log) gives the corrected scene without a new
        snapshot, and this costs the corrected frames' records only. Until that checkpoint is written
        the log counts fewer corrections than the archive, and a restart re-folds from the archive
        (`restore_session`). A failure makes the session read-only until a restart."""
        found = scan(self.log.path.read_bytes())
        head = found.records[0].offset if found.records and found.records[0].checkpoint else -1  # the snapshot's
        after = [r for r in found.records if not r.checkpoint and r.index >= first and r.offset > head]
        try:
            self.log.truncate(after[0].offset if after else found.end)
            for k, msg in enumerate(archive.messages(archive.entries[first:])):
                self.log.append(first + k, wire.pack(msg))
            self.log.append(self.snapshot_frames, checkpoint_payload(self.frame_ids, self._corrections()), checkpoint=True)
        except OSError as exc:
            self.wedged = f"{LOG}: {exc.strerror or exc}; the correction is durable, restart the service to apply it to the files"
            log.error("session %s: %s", self.id, self.wedged)

    def _bases(self, archive: SessionArchive, first: int) -> list[tuple[int, Path]]:
        """Saved states of the stream's first frames that a correction whose first touched frame is
        ``first`` may start from, latest first: the snapshot (it holds the stream's first
        ``snapshot_frames`` frames), and the state a correction kept (`BASE`) while no later
        correction touched a frame before it."""
        bases = [(self.snapshot_frames, self.path / SNAPSHOT)]
        try:
            meta = json.loads((self.path / BASE_META).read_text())
            if all(f >= meta["frames"] for f in archive.firsts[meta["corrections"]:]):
                bases.append((int(meta["frames"]), self.path / BASE))
        except (OSError, ValueError, KeyError, TypeError):
            pass
        return sorted(((n, path) for n, path in bases if 0 < n <= first), reverse=True)

    def _refolded(self, archive: SessionArchive, entries: list, changed: dict, removed: set, appearance,
                  bases: list[tuple[int, Path]], job: CorrectionJob | None = None) -> tuple[Scene, dict[int, bytes]]:
        """The corrected stream folded, from the latest saved state of its unchanged first frames
        (`_bases`; exact: a snapshot round-trips the state bit for bit), so a correction of recent
        frames costs the folds since that state. Also returns the latest states it started from or
        passed at multiples of `BASE_EVERY` (frame count -> `Scene.to_bytes`). With ``job``, counts its
        progress."""
        start, base, checkpoints = 0, None, LatestStates()
        for frames, path in bases:
            try:
                state = path.read_bytes()
                base = Scene.from_bytes(state)
            except (OSError, ValueError):
                continue
            if base.frames == frames:
                start, checkpoints[frames] = frames, state  # still a valid base after this correction
                break
            base = None
        stream = corrected_stream(archive.frames(entries[start:]), {k - start: c2w for k, c2w in changed.items()},
                                  {k - start for k in removed})
        if job is not None:
            job.total = len(entries) - len(removed) - start
            stream = counted(stream, job)
        if base is not None:
            base.keep_undo(self.undo_depth)  # the re-fold's last folds can be rolled back: a next correction of them is cheap
        else:
            base = Scene(self.config, undo_depth=self.undo_depth)
        self._preallocate(base)  # the re-fold and the scene it becomes grow into committed memory
        return Scene.refolded(self.config, stream, appearance, base, BASE_EVERY, checkpoints), checkpoints

    def _keep_base(self, checkpoints: dict[int, bytes]) -> None:
        """Keep the latest state the re-fold started from or passed before the scene's end (`BASE`),
        for the next correction of recent frames (the snapshot is about to hold the whole scene). Written after the correction is durable; a failure only costs
        that next correction a longer re-fold."""
        frames = max((n for n in checkpoints if n < self.scene.frames), default=0)
        if not frames:
            return
        try:
            write_atomic(self.path / BASE, checkpoints[frames])
            write_atomic(self.path / BASE_META, json.dumps({"frames": frames, "corrections": self._corrections()}).encode())
        except OSError as exc:
            log.warning("session %s: the re-fold's base state could not be kept (%s)", self.id, exc.strerror or exc)

    def _usable_archive(self) -> SessionArchive:
        if self.archive is not None:
            self.archive.flush()  # corrections read every frame the scene holds
        if self.archive is None:
            raise CorrectionRefused("archive_retention", "this session keeps no frame archive (retention 'none'), "
                                                         "so its poses cannot be corrected nor frames removed")
        if self.archive.problem:
            raise CorrectionRefused("archive_retention", self.archive.problem)
        return self.archive

    def _persist_correction(self) -> None:
        """Snapshot the corrected scene and restart the log with a checkpoint that counts the archive's
        corrections. A failure leaves the correction durable in the archive (a restart re-folds it), but
        the log cannot take frames on the old snapshot: the session is read-only until a restart."""
        self._snapshot()
        if self.snapshot_error or self.snapshot_frames != self.scene.frames:
            self.wedged = f"{self.snapshot_error}; the correction is durable, restart the service to apply it to the files"
            log.error("session %s: %s", self.id, self.wedged)

    def _check_alive(self) -> None:
        if self.deleted:
            raise SessionNotFound(self.id)

    # -- reading --------------------------------------------------------------------------------
    def gaussians(self, max_gaussians: int | None = None, features: bool = True) -> tuple[Gaussians, int]:
        """Decoded Gaussians (`Scene.gaussians`: decoded once per change; colour re-solves run on
        `COLOUR_SOLVES`; without ``features``, F_scene may be left out) and their label_dim."""
        with self.lock:
            self._check_alive()
            scene = self.scene
        g = scene.gaussians(max_gaussians, colour_solver=COLOUR_SOLVES, features=features)
        return g, 0 if g.labels is None else int(g.labels.shape[1])

    @property
    def retention(self) -> str:
        return self.archive.retention if self.archive is not None else "none"

    def summary(self) -> dict:
        return {"id": self.id, "frames": self.scene.frames, "voxels": len(self.scene), "created": self.created,
                "archive_retention": self.retention, "state": "read_only" if self.wedged else "ok", "problem": self.wedged}

    def stats(self) -> dict:
        gaussians = len(self.gaussians(features=False)[0])  # a decode if none is cached, outside the scene's lock
        with self.lock:
            self._check_alive()
            stats = self.scene.stats()
            archive = self.archive
            return {
                "archive_retention": self.retention,
                "archive_bytes": archive.nbytes() if archive is not None else 0,
                "archive_frames": sum(e.kept for e in archive.entries) if archive is not None else 0,
                "archive_problem": archive.problem if archive is not None else None,
                **self.summary(),
                "gaussians": gaussians,
                "memory_bytes": stats["memory_bytes"],
                "undo_bytes": self.scene.undo_bytes(),
                "disk_bytes": sum(p.stat().st_size for p in self.path.iterdir() if p.is_file()),
                "label_dim": stats["label_dim"],
                "inconsistent_depth_below": stats["inconsistent_depth_below"],
                "snapshot_frames": self.snapshot_frames,
                "snapshot_error": self.snapshot_error,
                "config": self.config.to_dict(),
            }

    def digest(self) -> dict:
        """The library's digest of the fused state: equal iff the sessions fused the same frames."""
        with self.lock:
            self._check_alive()
            return {"id": self.id, "frames": self.scene.frames, "voxels": len(self.scene), "sha256": self.scene.digest()}


def counted(frames, job: CorrectionJob):
    """``frames``, counting each one in ``job.refolded`` as the re-fold takes the next."""
    for frame in frames:
        yield frame
        job.refolded += 1


class LatestStates(dict):
    """Frame count -> state bytes, holding the two latest only: the states a re-fold passes cost a
    whole scene each, and a correction keeps one, from before the scene's end."""

    def __setitem__(self, frames: int, state: bytes) -> None:
        super().__setitem__(frames, state)
        while len(self) > 2:
            del self[min(self)]


def _remove_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def checkpoint_payload(frame_ids: dict[str, FoldedFrame], corrections: int = 0) -> bytes:
    """The checkpoint's payload: the frame-id table and how many archived corrections the snapshot holds."""
    return msgpack.packb({"frame_ids": {k: [v.index, v.digest, v.report] for k, v in frame_ids.items()},
                          "corrections": corrections})


def _corrections_of(path: Path) -> int:
    """How many archived corrections the snapshot holds, by the log's last checkpoint (0 without one)."""
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    checkpoints = [r for r in scan(data).records if r.checkpoint]
    return int(msgpack.unpackb(checkpoints[-1].payload).get("corrections", 0)) if checkpoints else 0


def archived_frame_ids(archive: SessionArchive, known: dict[str, FoldedFrame]) -> dict[str, FoldedFrame]:
    """The frame-id table after a correction: the archive's frames with their new positions; a
    removed frame's id is forgotten (sending it again folds it again). Reports keep their counts."""
    out = {}
    for position, e in enumerate(archive.entries):
        if e.frame_id is not None:
            report = (known.get(e.frame_id) or FoldedFrame(0, "", None)).report
            out[e.frame_id] = FoldedFrame(position, e.digest, report and {**report, "frame_index": position})
    return out


def restore_session(path: Path, config: SceneConfig, retention: Retention) -> tuple[Restored, SessionArchive | None]:
    """`restore_scene`, with the session's frame archive. When the archive holds a correction that the
    snapshot does not (a crash between archiving a correction and snapshotting its scene), the scene is
    re-folded from the archive and snapshotted, so a restart gives the corrected scene, never a mixture."""
    archive = SessionArchive(path / ARCHIVE, retention) if retention != "none" else None
    if archive is None or archive.problem or archive.corrections <= _corrections_of(path):
        restored = restore_scene(path, config)
        if archive is not None and archive.problem is None:
            archive.cut_to(restored.scene.frames, logged_frames(path))
        return restored, archive
    snap = path / SNAPSHOT
    scene = Scene.load(snap) if snap.exists() else Scene(config)
    entries = list(archive.entries)
    dropped = {k for k, e in enumerate(entries) if not e.kept}
    scene.adopt(Scene.refolded(config, corrected_stream(archive.frames(entries), {}, dropped), scene.appearance))
    if dropped:
        archive.append_correction({}, [entries[k].arrival for k in dropped], min(dropped))
    frame_ids = archived_frame_ids(archive, {})
    write_atomic(snap, scene.to_bytes())
    write_atomic(path / LOG, encode(scene.frames, checkpoint_payload(frame_ids, archive.corrections), checkpoint=True))
    log.warning("%s: re-folded %d frames from the archive (a correction the snapshot did not hold)", path, scene.frames)
    return Restored(scene, FrameLog(path / LOG), scene.frames, frame_ids), archive


def logged_frames(path: Path) -> dict[int, bytes]:
    """The frame log's frames: stream position -> wire payload (what a restart archives when the
    archive had not caught up with them)."""
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    return {r.index: r.payload for r in scan(data).records if not r.checkpoint}


def _frame_ids_of(checkpoint: bytes) -> dict[str, FoldedFrame]:
    table = msgpack.unpackb(checkpoint)["frame_ids"]
    return {k: FoldedFrame(index, digest, report) for k, (index, digest, report) in table.items()}


def quarantine(path: Path, data: bytes) -> Path:
    """A copy of a damaged log under ``quarantine/`` (one per distinct content), so nothing is lost."""
    folder = path / QUARANTINE
    folder.mkdir(exist_ok=True)
    target = folder / f"{LOG}.{hashlib.blake2b(data, digest_size=8).hexdigest()}"
    if not target.exists():
        write_atomic(target, data)
    return target


def restore_scene(path: Path, config: SceneConfig) -> Restored:
    """Load the snapshot (if any) and replay the log after it. Raises `Unrestorable` when the files do
    not add up: a damaged log (quarantined first), a missing log, a snapshot missing or older than the
    log says."""
    for stale in path.glob(PENDING_SNAPSHOT.format("*") + "*"):  # written off the acknowledged path, never committed
        _remove_quietly(stale)
    if not (path / LOG).is_file():
        raise Unrestorable(f"{LOG} is missing: frames after the last snapshot may be lost "
                           "(`canonical repair` starts an empty log)")
    data = (path / LOG).read_bytes()
    found = scan(data)
    if found.damaged:
        try:
            where = f"copied to {quarantine(path, data)}"
        except OSError as exc:
            where = f"could not be copied aside ({exc.strerror or exc}); it is left as it is"
        raise Unrestorable(f"{LOG}: {found.describe()}; the log {where}. `canonical repair --action truncate` "
                           "keeps the frames before the damage, `--action skip` every intact frame")
    snap = path / SNAPSHOT
    try:
        scene = Scene.load(snap) if snap.exists() else Scene(config)
    except ValueError as exc:
        raise Unrestorable(f"{SNAPSHOT}: {exc}; restore it from a backup") from None
    snapshot_frames = scene.frames
    checkpoints = [r for r in found.records if r.checkpoint]
    records = [r for r in found.records if not r.checkpoint]
    first = checkpoints[-1].index if checkpoints else (records[0].index if records else 0)
    if first > scene.frames:
        what = "missing" if not snap.exists() else f"older than the log (it holds {scene.frames} frames)"
        raise Unrestorable(f"{SNAPSHOT} is {what}: the log continues from frame {first}, so frames "
                           f"{scene.frames}..{first - 1} are not on disk. Restore {SNAPSHOT} from a backup, or "
                           "`canonical repair` keeps the log's frames without them")
    frame_log = FrameLog(path / LOG)
    if found.torn:
        log.warning("%s: cutting off a torn log tail (%d bytes at offset %d, never acknowledged)", path,
                    found.size - found.end, found.end)
        frame_log.truncate(found.end)
    frame_ids = _frame_ids_of(checkpoints[-1].payload) if checkpoints else {}
    for k, record in enumerate(records):
        try:
            if record.index > scene.frames:
                raise ValueError(f"log: record for frame {record.index} follows frame {scene.frames - 1}")
            msg = wire.unpack(record.payload)
            # a record the snapshot holds already (a crash between snapshot and log restart) only adds its id
            report = scene.fold(wire.frame_from_message(msg)).to_dict() if record.index == scene.frames else None
        except ValueError as exc:
            if k != len(records) - 1:
                # Records after it exist, so this one was folded and acknowledged once: never drop it
                # (e.g. a library that validates more strictly now). The session is not served.
                frame_log.close()
                raise Unrestorable(f"{LOG}: acknowledged frame {record.index} no longer folds: {exc}") from exc
            # the last record's fold failed: it was never acknowledged (the crash came before its truncation)
            log.warning("%s: dropping the unacknowledged last log record (frame %d): %s", path, record.index, exc)
            frame_log.truncate(record.offset)
            break
        if msg.get("frame_id") is not None:  # a frame the checkpoint names was rewritten by a correction: its digest stays
            known = frame_ids.get(msg["frame_id"])
            digest = known.digest if known is not None else payload_digest(record.payload)
            frame_ids[msg["frame_id"]] = FoldedFrame(record.index, digest, report)
    return Restored(scene, frame_log, snapshot_frames, frame_ids)


def repair(path: Path, action: RepairAction) -> str:
    """Make an unrestorable session's files add up again, keeping every frame that can be kept (see
    `server.framelog.repaired`); the log as it was stays under ``quarantine/``. Returns what it did."""
    snap = path / SNAPSHOT
    try:
        snapshot_frames = Scene.load(snap).frames if snap.exists() else 0
    except ValueError as exc:
        raise Unrestorable(f"{SNAPSHOT}: {exc}; restore it from a backup (repair cannot rebuild it)") from None
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    if data:
        quarantine(path, data)
    found = scan(data)
    checkpoints = [r for r in found.records + found.later if r.checkpoint]
    records, kept, dropped = repaired(data, action, snapshot_frames, checkpoints[-1].payload if checkpoints else None)
    write_atomic(path / LOG, b"".join(records))
    return (f"the snapshot's {snapshot_frames} frames and {kept} logged frames after them kept; {dropped} intact "
            f"frames after the damage dropped (the old log is under {QUARANTINE}/)")


class SessionStore:
    """All sessions of one data directory, which it locks: one server per directory."""

    session_class = Session  # what `create` makes (`server.cluster` makes sessions that hold a lease)

    def __init__(self, data_dir: str | os.PathLike, max_sessions: int, threads: int | None = None,
                 retention: Retention = "all"):
        self.data_dir = Path(data_dir)
        self.retention = retention  # the frame archive's retention of sessions created without one
        self.background_frames = BACKGROUND_FRAMES  # corrections that re-fold more run in the background
        self.undo_depth: int | None = None  # folds a session's scene can roll back in place (None: UNDO_DEPTH)
        self.preallocate_voxels = 0  # voxels whose memory a session's scene commits up front
        self.root = self.data_dir / "sessions"
        self.max_sessions = max_sessions
        self.threads = threads
        self._sessions: dict[str, Session] = {}
        self.unavailable: dict[str, str] = {}  # session id -> why its files do not add up
        self._lock = threading.Lock()  # guards the dict and the session count
        self._dir_lock: int | None = None

    def lock_dir(self) -> None:
        """Take the data directory's lock (released when the process ends, kill -9 included)."""
        if self._dir_lock is not None:
            return
        self.root.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.data_dir / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise DataDirLocked(f"data_dir: {self.data_dir} is in use by another server (pid {holder}); "
                                "one server per data directory") from None
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._dir_lock = fd

    def open(self) -> None:
        """Lock the directory and load every session on disk (snapshot + log replay); clean up
        half-created or deleted ones; list the ones whose files do not add up as unavailable."""
        configure_thread(self.threads)
        self.lock_dir()
        for path in sorted(self.root.iterdir()):
            if not path.is_dir():
                continue
            if path.name.startswith(TOMBSTONE):
                shutil.rmtree(path, ignore_errors=True)
                continue
            if not (path / META).is_file():
                if {p.name for p in path.iterdir()} <= {LOG, ARCHIVE} and not any(p.stat().st_size for p in path.iterdir()):
                    log.warning("%s: no %s and nothing logged (creation never completed); removing it", path, META)
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    self._unavailable(path.name, f"{META} is missing; restore it from a backup (the other files are kept)")
                continue
            t0 = time.perf_counter()
            try:
                meta = json.loads((path / META).read_text())
                config = SceneConfig.from_dict(meta["config"])
                restored, archive = restore_session(path, config, meta.get("archive_retention", "all"))
            except Unrestorable as exc:
                self._unavailable(path.name, str(exc))
                continue
            except Exception as exc:  # one unreadable session (e.g. a snapshot of a future version) must not stop the rest
                log.exception("%s: cannot be restored", path)
                self._unavailable(path.name, f"cannot be restored ({type(exc).__name__}: {exc})")
                continue
            self._sessions[meta["id"]] = Session(meta["id"], path, config, meta["created"], *restored, archive=archive,
                                                 **self._session_options())
            log.info("session %s…: %d frames (%d replayed) in %.2fs", meta["id"][:6], restored.scene.frames,
                     restored.scene.frames - restored.snapshot_frames, time.perf_counter() - t0)

    def repair(self, session_id: str, action: RepairAction | None) -> str:
        """Repair one session's files offline (the directory's lock held: no server runs on it); with
        ``action`` None only say what is wrong. Returns what it found or did."""
        self.lock_dir()
        path = self.root / session_id
        if session_id.startswith(TOMBSTONE) or not path.is_dir():
            raise ValueError(f"session: no session {session_id!r} in {self.root}")
        if not (path / META).is_file():
            raise ValueError(f"session: {META} is missing; restore it from a backup (repair needs its settings)")
        config = SceneConfig.from_dict(json.loads((path / META).read_text())["config"])
        try:
            restore_scene(path, config).log.close()
            return f"session {session_id}: nothing to repair"
        except Unrestorable as exc:
            if action is None:
                raise ValueError(f"action: session {session_id} needs repair: {exc}") from None
        done = repair(path, action)
        restored = restore_scene(path, config)
        restored.log.close()
        return f"session {session_id}: {done}; it now holds {restored.scene.frames} frames"

    def unavailable_summaries(self) -> list[dict]:
        def created(session_id: str) -> float:
            try:
                return json.loads((self.root / session_id / META).read_text())["created"]
            except (OSError, ValueError, KeyError):
                return 0.0

        return [{"id": i, "frames": None, "voxels": None, "created": created(i), "state": "unavailable", "problem": reason}
                for i, reason in sorted(self.unavailable.items())]

    def _unavailable(self, session_id: str, reason: str) -> None:
        log.error("session %s is not served: %s", session_id, reason)
        self.unavailable[session_id] = reason

    def close(self) -> None:
        """Snapshot sessions with unsnapshotted frames (a faster next start), close their logs, unlock."""
        try:
            for session in self.list():
                try:
                    session.wait_for_snapshot()  # one being written lands first: then nothing, or little, is left
                    session.snapshot()
                finally:
                    session.log.close()
                    if session.archive is not None:
                        session.archive.close()
        finally:
            if self._dir_lock is not None:
                os.close(self._dir_lock)
                self._dir_lock = None

    def create(self, config: SceneConfig, retention: Retention | None = None) -> Session:
        """A new, empty session; ``retention``: its frame archive's (None: the store's default)."""
        retention = self.retention if retention is None else retention
        if retention not in RETENTIONS:
            raise ValueError(f"archive_retention: expected one of {list(RETENTIONS)}, got {retention!r}")
        with self._lock:
            if len(self._sessions) >= self.max_sessions:
                raise TooManySessions(f"max_sessions: the service holds {len(self._sessions)} sessions, its limit")
            scene = Scene(config)  # before any file: a config whose model cannot load leaves nothing behind
            session_id = self.new_session_id()
            path = self.root / session_id
            created = time.time()
            meta = {"format": "canonicalgs-session", "version": 1, "id": session_id, "created": created, "config": config.to_dict(),
                    "archive_retention": retention}
            try:
                path.mkdir()
                frame_log = FrameLog(path / LOG)
                archive = SessionArchive(path / ARCHIVE, retention) if retention != "none" else None
                write_atomic(path / META, json.dumps(meta, indent=1).encode())
            except OSError as exc:
                shutil.rmtree(path, ignore_errors=True)
                raise StorageError(f"{META}: cannot create the session", exc) from exc
            session = self.session_class(session_id, path, config, created, scene, frame_log, 0, archive=archive,
                                         **self._session_options())
            self._sessions[session_id] = session
            return session

    def _session_options(self) -> dict:
        """The store's settings that its sessions carry."""
        undo = {} if self.undo_depth is None else {"undo_depth": self.undo_depth}
        return {"background_frames": self.background_frames, "preallocate_voxels": self.preallocate_voxels, **undo}

    def new_session_id(self) -> str:
        return secrets.token_hex(16)  # not urlsafe: an id that starts with '-' reads as a CLI flag

    def get(self, session_id: str) -> Session:
        session = self._sessions.get(session_id)
        if session is None:
            if session_id in self.unavailable:
                raise SessionUnavailable(session_id, self.unavailable[session_id])
            raise SessionNotFound(session_id)
        return session

    def list(self) -> list[Session]:
        with self._lock:
            return sorted(self._sessions.values(), key=lambda s: s.created)

    def __len__(self) -> int:
        return len(self._sessions)

    def delete(self, session_id: str) -> None:
        """Delete a session and its files (an unavailable one too: deleting is one way to resolve it)."""
        if session_id in self.unavailable:
            with self._lock:
                self._bury(self.root / session_id)
                del self.unavailable[session_id]
            return
        session = self.get(session_id)
        with session.lock:
            session._check_alive()
            session.deleted = True
            session.log.close()
            if session.archive is not None:
                session.archive.close()
            with self._lock:
                self._sessions.pop(session_id, None)
            self._bury(session.path)

    def _bury(self, path: Path) -> None:
        tomb = self.root / f"{TOMBSTONE}{path.name}"
        os.replace(path, tomb)  # atomic: a crash from here on leaves only a tombstone
        fsync_dir(self.root)
        shutil.rmtree(tomb, ignore_errors=True)

    def snapshot_due(self, every_seconds: float) -> int:
        """Snapshot sessions whose oldest unsnapshotted frame is older than ``every_seconds``."""
        now, done = time.monotonic(), 0
        for session in self.list():
            since = session.dirty_since
            if since is not None and now - since >= every_seconds:
                session.snapshot(background=True)
                done += 1
        return done

    def totals(self) -> dict:
        sessions = self.list()
        return {"sessions": len(sessions), "voxels": sum(len(s.scene) for s in sessions),
                "frames": sum(s.scene.frames for s in sessions), "unavailable": len(self.unavailable),
                "wedged": sum(s.wedged is not None for s in sessions),
                "snapshot_failures": sum(s.snapshot_failures for s in sessions)}


__all__ = ["CorrectionRefused", "DataDirLocked", "FrameIdConflict", "FrameLog", "Session", "SessionNotFound", "SessionStore", "SessionUnavailable",
           "StorageError", "TooManySessions", "Unrestorable", "configure_thread", "repair"]
