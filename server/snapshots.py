"""A session's snapshots: when one is due, how a due one is written off the acknowledged path, and
the log's restart after each (the files themselves: `server.durability`).

The frame that makes a snapshot due copies the state (`Scene.snapshot_parts`) and is answered; a
writer thread encodes it into ``scene.snap.<n>.next`` (fsynced) and then, under the session's lock,
renames it to ``scene.snap`` and restarts the log. A crash before that rename leaves the previous
snapshot and the whole log (the ``.next`` file is removed on start).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass

from canonical_core.scene import Scene

from .durability import PENDING_SNAPSHOT, SNAPSHOT, remove_quietly
from .framelog import encode, fsync_dir, write_atomic

log = logging.getLogger("canonical.store")  # the store's logger: one name for all that the store holds

SNAPSHOT_RETRY_SECONDS = 30.0  # after a failed snapshot, folds do not try again sooner (each try writes it all)


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


class Snapshots:
    """The snapshot of one session (`server.session.Session`) and its schedule. It works on the
    session's ``scene``, ``log``, ``archive`` and checkpoint (`Session.checkpoint`); none is taken
    while a correction re-folds in the background (``corrections.background``). The methods but
    `wait` expect the caller to hold the session's ``lock``; the writer thread takes it to commit,
    skips a session that is ``deleted`` meanwhile and bumps its ``version``."""

    write_off_path = True  # due snapshots are written off the acknowledged path

    def __init__(self, session, frames: int):
        self.session = session
        self.frames = frames  # the snapshot holds the stream's first ``frames`` frames
        self.dirty_since: float | None = None  # when the oldest frame not in the snapshot was folded
        self.error: str | None = None  # why the last snapshot failed (frames stay durable in the log)
        self.failures = 0
        self.retry_at = 0.0  # monotonic time before which a fold does not retry a failed snapshot
        self.pending: PendingSnapshot | None = None  # the snapshot being written off the acknowledged path
        self.started = 0  # numbers the pending snapshots' files

    def after_fold(self, every_frames: int, every_seconds: float) -> None:
        """A frame was folded: start a snapshot if one is due (``every_frames`` frames since the
        last, or ``every_seconds`` since the oldest frame it lacks), unless one failed lately."""
        now = time.monotonic()
        self.dirty_since = self.dirty_since or now
        if now >= self.retry_at and (self.session.scene.frames - self.frames >= every_frames
                                     or now - self.dirty_since >= every_seconds):
            self.soon()

    def take(self) -> None:
        """Snapshot, then start the log afresh with a checkpoint. A failure is recorded, not raised: every
        frame is durable in the log already, and the next due snapshot tries again. None while a
        correction re-folds in the background: its swap snapshots (the saved states it starts from
        stay as they are, and a restart before it re-folds from the archive)."""
        session = self.session
        if session.corrections.background is not None:
            return
        self.cancel()
        try:
            write_atomic(session.path / SNAPSHOT, session.scene.to_bytes())
        except OSError as exc:
            self._failed(exc)
            return
        self.frames, self.dirty_since, self.error = session.scene.frames, None, None
        self._restart_log(self.frames, session.checkpoint(), b"")

    def _failed(self, exc: Exception) -> None:
        self.error = f"{SNAPSHOT}: {getattr(exc, 'strerror', None) or exc}"
        self.failures += 1
        self.retry_at = time.monotonic() + SNAPSHOT_RETRY_SECONDS
        log.error("session %s: snapshot failed (%s); its frames stay in the log", self.session.id, self.error)

    def _restart_log(self, frames: int, checkpoint: bytes, tail: bytes) -> None:
        """The log replaced by a checkpoint of the snapshot's ``frames`` and ``tail`` (the records of
        the frames after them), once the archive holds every frame."""
        session = self.session
        if session.archive is not None:
            session.archive.flush()  # the log is restarted below: the archive must hold its frames first
            if session.archive.problem is not None:
                return  # the log keeps the frames the archive may lack: a restart archives them from it
        try:
            session.log.reset([encode(frames, checkpoint, checkpoint=True), tail])
        except OSError as exc:  # the old records stay; a restart skips those the snapshot holds
            log.error("session %s: the log could not be restarted after a snapshot (%s)", session.id,
                      exc.strerror or exc)

    def soon(self) -> None:
        """A due snapshot, off the acknowledged path. Here the state is copied (`Scene.snapshot_parts`:
        the sums, a memory copy); a writer thread encodes it and writes it to its own file (fsynced),
        then, under the lock, commits it: the file becomes the snapshot and the log keeps only the
        records after it. The frames folded meanwhile stay in the log; a crash before the commit
        restarts from the previous snapshot and the whole log. One at a time."""
        if not self.write_off_path:
            self.take()
            return
        session = self.session
        if self.pending is not None or session.corrections.background is not None:
            return
        parts = session.scene.snapshot_parts()
        self.started += 1
        pending = PendingSnapshot(self.started, session.scene.frames, session.log.size(), session.checkpoint(),
                                  time.monotonic())
        self.pending = pending
        pending.writer = threading.Thread(target=self._write_pending, args=(pending, parts), daemon=True,
                                          name=f"snapshot-{session.id[:8]}")
        pending.writer.start()

    def wait(self, timeout: float | None = None) -> None:
        """Wait until the snapshot being written, if any, is committed or dropped (not with the lock held:
        its writer takes it to commit)."""
        pending = self.pending
        if pending is not None and pending.writer is not None:
            pending.writer.join(timeout)

    def _write_pending(self, pending: PendingSnapshot, parts: tuple[dict, dict]) -> None:
        session = self.session
        path = session.path / PENDING_SNAPSHOT.format(pending.number)
        try:  # encoded straight into the file: no second copy of the state in memory
            write_atomic(path, lambda f: Scene.encode_snapshot(*parts, out=f))
            error = None
        except Exception as exc:  # noqa: BLE001 - recorded like a failed snapshot; the frames stay in the log
            error = exc
        del parts
        with session.lock:
            if self.pending is pending:
                self.pending = None
            if pending.cancelled or session.deleted or error is not None:
                remove_quietly(path)
                if error is not None and not pending.cancelled and not session.deleted:
                    self._failed(error)
                return
            try:
                os.replace(path, session.path / SNAPSHOT)
                fsync_dir(session.path)
            except OSError as exc:
                remove_quietly(path)
                self._failed(exc)
                return
            self.frames, self.error = pending.frames, None
            self.dirty_since = None if session.scene.frames == pending.frames else pending.captured
            session.version += 1  # a correction computed from the snapshot before this one is refused
            try:
                with open(session.log.path, "rb") as f:  # the records of the frames folded meanwhile
                    f.seek(pending.log_offset)
                    tail = f.read()
            except OSError as exc:  # the old records stay; a restart skips those the snapshot holds
                log.error("session %s: the log could not be read after a snapshot (%s)", session.id,
                          exc.strerror or exc)
                return
            self._restart_log(pending.frames, pending.checkpoint, tail)

    def cancel(self) -> None:
        """The session's files are about to change otherwise (a snapshot now, a correction, a reload):
        the snapshot being written is never committed (its writer removes its file)."""
        if self.pending is not None:
            self.pending.cancelled = True
            self.pending = None
