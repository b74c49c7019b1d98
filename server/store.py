"""The session store: the sessions of one data directory, and the directory's lock. No HTTP here.

Layout: ``<data_dir>/.lock`` (held by the one server that uses the directory), and one folder per
session under ``<data_dir>/sessions/<id>/``: ``meta.json`` (id, creation time, the SceneConfig and its
digest, written once, atomically), the frame log and the snapshot (`server.durability`), the frame archive
(`server.archive`) and a correction's saved state (`server.corrections`). A deleted session's folder
is renamed to a tombstone first, so a crash mid-delete leaves nothing that looks like a session.

A session whose files do not add up on start (damaged log, a log or snapshot removed by hand, an
unreadable snapshot, a missing meta.json) is listed as unavailable with the reason, and its requests
get that reason; its files are left as they are.

Locks: the store's own lock guards its set of sessions; a session's lock (`server.session`) is taken
before it where both are held (a deletion).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import secrets
import shutil
import threading
import time
import weakref
from pathlib import Path
from typing import Callable

import numba

from canonical_core import SceneConfig
from canonical_core.scene import Scene

from .archive import ARCHIVE, RETENTIONS, Retention, SessionArchive
from .corrections import BACKGROUND_FRAMES
from .durability import (LOG, META, config_digest, remove_quietly, restore_session, restored_frames,
                         session_meta)
from .framelog import FrameLog, RepairAction, StorageError, fsync_dir, write_atomic
from .memory import MemoryBudget, release_memory
from .retention import prune as prune_idle
from .repair import repair
from .session import Session
from .session_errors import DataDirLocked, SessionNotFound, SessionUnavailable, TooManySessions, Unrestorable

log = logging.getLogger("canonical.store")

LOCK = ".lock"
TOMBSTONE = ".deleted-"


def configure_thread(threads: int | None) -> None:
    """Apply the ``threads`` setting in the calling thread (numba's count is per thread)."""
    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


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
        self.budget: MemoryBudget | None = None  # the memory its sessions' folds reserve from (None: unbounded)
        self.root = self.data_dir / "sessions"
        self.max_sessions = max_sessions
        self.threads = threads
        self._sessions: dict[str, Session] = {}
        self.unavailable: dict[str, str] = {}  # session id -> why its files do not add up
        self._lock = threading.Lock()  # guards the dict and the session count
        self._dir_lock: int | None = None
        # deleted sessions that a job still held when they were deleted (a render, a snapshot's writer):
        # their memory goes back once it lets go (`release_departed`)
        self._departed: list[weakref.ref] = []

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
            for stale in path.glob("*.tmp"):  # an atomic write's temporary file, left by a crash mid-write
                remove_quietly(stale)
            if not (path / META).is_file():
                if {p.name for p in path.iterdir()} <= {LOG, ARCHIVE} and not any(p.stat().st_size for p in path.iterdir()):
                    log.warning("%s: no %s and nothing logged (creation never completed); removing it", path, META)
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    self._unavailable(path.name, f"{META} is missing; restore it from a backup (the other files are kept)")
                continue
            t0 = time.perf_counter()
            try:
                meta, config = session_meta(path)
                restored, archive = restore_session(path, config, meta.get("archive_retention", "all"),
                                                     meta.get("chosen"))
            except Unrestorable as exc:
                self._unavailable(path.name, str(exc))
                continue
            except Exception as exc:  # one unreadable session (e.g. a snapshot of a future version) must not stop the rest
                log.exception("%s: cannot be restored", path)
                self._unavailable(path.name, f"cannot be restored ({type(exc).__name__}: {exc})")
                continue
            self._sessions[meta["id"]] = Session(meta["id"], path, config, meta["created"], *restored, archive=archive,
                                                 chosen=meta.get("chosen", {}), **self._session_options())
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
        meta, config = session_meta(path)  # settings edited by hand are not for repair to fix: raised as they are
        retention = meta.get("archive_retention", "all")
        try:
            restored_frames(path, config, retention)  # what a start would find: the log and its archive
            return f"session {session_id}: nothing to repair"
        except Unrestorable as exc:
            if action is None:
                raise ValueError(f"action: session {session_id} needs repair: {exc}") from None
        done = repair(path, action)
        return f"session {session_id}: {done}; it now holds {restored_frames(path, config, retention)} frames"

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

    def close(self, snapshot: bool = True) -> None:
        """Snapshot sessions with unsnapshotted frames (a faster next start; not with ``snapshot`` False),
        close their logs, unlock."""
        try:
            for session in self.list():
                try:
                    session.snapshots.wait()  # one being written lands first: then nothing, or little, is left
                    if snapshot:
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
            config = scene.config  # a named sensor family's values are known now (`Scene.chosen`)
            session_id = self.new_session_id()
            path = self.root / session_id
            created = time.time()
            meta = {"format": "canonicalgs-session", "version": 1, "id": session_id, "created": created, "config": config.to_dict(),
                    "config_sha256": config_digest(config.to_dict()), "archive_retention": retention}
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
        return {"background_frames": self.background_frames, "preallocate_voxels": self.preallocate_voxels,
                "budget": self.budget, **undo}

    def memory_in_use(self) -> int:
        """Bytes the held sessions' scenes hold (`Scene.memory_bytes`). Takes no lock: it is read
        under the budget's lock, and a session created or dropped meanwhile moves it by one scene."""
        return sum(s.scene.memory_bytes() for s in list(self._sessions.values()))

    def new_session_id(self) -> str:
        return secrets.token_hex(16)  # not urlsafe: an id that starts with '-' reads as a CLI flag

    def frame_refused(self, session_id: str, index: int, why: str) -> None:
        """Numbered frame ``index`` of a held session was refused before its route ran (its body: too
        large, too slow): the frames numbered after it stop waiting for it (`routes.frames.body_refused`)."""
        session = self.find(session_id)
        if session is not None:
            session.order.refused(index, ValueError(why))

    def find(self, session_id: str) -> Session | None:
        """The loaded session of this id, or None."""
        return self._sessions.get(session_id)

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

    def delete(self, session_id: str, keep_if: Callable[[Session], bool] | None = None) -> bool:
        """Delete a session and its files (an unavailable one too: deleting is one way to resolve it).
        With ``keep_if`` (retention's removals) a session whose lock is held is kept, and so is one for
        which ``keep_if`` says so under its lock; returns whether it was deleted."""
        if session_id in self.unavailable and keep_if is None:
            with self._lock:
                self._bury(self.root / session_id)
                del self.unavailable[session_id]
            return True
        session = self.get(session_id)
        if not session.lock.acquire(blocking=keep_if is None):
            return False
        try:
            session.check_alive()
            if keep_if is not None and keep_if(session):
                return False
            tomb = self._entomb(session.path)  # files first: a session gone from the listing is gone from disk
            session.deleted = True
            session.log.close()
            if session.archive is not None:
                session.archive.close()
            with self._lock:
                self._sessions.pop(session_id, None)
            shutil.rmtree(tomb, ignore_errors=True)
        finally:
            session.lock.release()
        departed = weakref.ref(session)
        del session
        release_memory()
        if departed() is not None:
            with self._lock:
                self._departed.append(departed)
        return True

    def release_departed(self) -> int:
        """Give back the memory of deleted sessions whose last holder has let go since their deletion
        (the delete's own release found them held; a session and its snapshots and corrections refer
        to each other, so only the cycle collector frees it). Run periodically; returns how many are
        still held. Nothing is collected while no deleted session is pending (one its holder released
        itself, as a background solve does, is no longer)."""
        with self._lock:
            self._departed = [departed for departed in self._departed if departed() is not None]
            if not self._departed:
                return 0
        release_memory()
        with self._lock:
            self._departed = [departed for departed in self._departed if departed() is not None]
            return len(self._departed)

    def prune(self, ttl_s: float | None, budget_bytes: int | None, dry_run: bool = False) -> dict:
        """Remove idle sessions by the retention policy (`server.retention`); returns its report."""
        return prune_idle(self, ttl_s, budget_bytes, dry_run)

    def _bury(self, path: Path) -> None:
        shutil.rmtree(self._entomb(path), ignore_errors=True)

    def _entomb(self, path: Path) -> Path:
        """``path`` renamed to its tombstone (atomic: a crash from here on leaves only a tombstone, which
        the next start removes); `StorageError` where it cannot be, with nothing changed."""
        tomb = self.root / f"{TOMBSTONE}{path.name}"
        try:
            os.replace(path, tomb)
        except OSError as exc:
            raise StorageError(f"{path.name}: cannot delete its files", exc) from None
        with contextlib.suppress(OSError):  # the rename stands; only its durability through a power cut is in doubt
            fsync_dir(self.root)
        return tomb

    def snapshot_due(self, every_seconds: float) -> int:
        """Snapshot sessions whose oldest unsnapshotted frame is older than ``every_seconds``."""
        now, done = time.monotonic(), 0
        for session in self.list():
            since = session.snapshots.dirty_since
            if since is not None and now - since >= every_seconds:
                session.snapshot(background=True)
                done += 1
        return done

    def totals(self) -> dict:
        sessions = self.list()
        counts = [s.counts() for s in sessions]
        return {"sessions": len(sessions), "voxels": sum(v for _, v in counts),
                "frames": sum(f for f, _ in counts), "unavailable": len(self.unavailable),
                "wedged": sum(s.wedged is not None for s in sessions),
                "snapshot_failures": sum(s.snapshots.failures for s in sessions)}

