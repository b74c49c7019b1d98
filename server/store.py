"""The session store: sessions on disk and their locks. No HTTP here.

Layout, one folder per session under ``<data_dir>/sessions/<id>/``:

- ``meta.json``: id, creation time and the SceneConfig, written once, atomically.
- ``frames.log``: append-only frame log. A record is ``magic "CGF1" | u32 payload length | u64 frame
  index | u32 CRC-32 of (length, index, payload) | payload`` (little-endian); the payload is the frame's
  msgpack message as `server.wire.frame_from_message` reads it. A frame is appended and fsynced
  before it is folded and acknowledged; a record whose fold fails is truncated away again. On start a
  torn or corrupt tail (a crash mid-append: never acknowledged) is detected by length/CRC and cut off.
- ``scene.snap``: `Scene.save` snapshot (atomic), holding ``scene.frames`` frames. Written every
  ``snapshot_every_frames`` frames or ``snapshot_every_seconds``, and on shutdown; after it the log
  is emptied (its records are all in the snapshot). Restart = load snapshot, replay records whose
  index >= the snapshot's frame count. Folding is deterministic, so the replayed scene equals the
  uninterrupted one bit for bit.

Locks: ``Session.lock`` serialises what reads or writes one session's scene and files (fold,
snapshot, digest); rendering works on decoded Gaussians outside it, so a render never sees a
half-folded scene and never blocks another session. Decoded Gaussians come from `Scene.gaussians`,
which decodes once per change and holds the scene's own lock only to copy its sums, so folds go on
while a decode (and its colour solve) runs.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numba

from canonical_core import Frame, Gaussians, SceneConfig
from canonical_core.scene import FoldReport, Scene

from . import wire

log = logging.getLogger("canonical.store")

META, LOG, SNAPSHOT = "meta.json", "frames.log", "scene.snap"
TOMBSTONE = ".deleted-"


class SessionNotFound(KeyError):
    def __init__(self, session_id: str):
        super().__init__(session_id)
        self.session_id = session_id


class TooManySessions(RuntimeError):
    pass


# -- files ---------------------------------------------------------------------------------------
def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    fsync_dir(path.parent)


class FrameLog:
    """The append-only, CRC-checked frame log of one session (see the module docstring)."""

    MAGIC = b"CGF1"
    HEADER = struct.Struct("<4sIQI")

    def __init__(self, path: Path):
        self.path = path
        self._file = open(path, "ab")

    @classmethod
    def _crc(cls, length: int, index: int, payload: bytes) -> int:
        return zlib.crc32(payload, zlib.crc32(struct.pack("<IQ", length, index)))

    def records(self) -> list[tuple[int, int, bytes]]:
        """(offset, frame index, payload) of every intact record; a torn or corrupt tail is cut off."""
        data = self.path.read_bytes()
        out, pos, size = [], 0, self.HEADER.size
        while pos < len(data):
            if len(data) - pos < size:
                break
            magic, length, index, crc = self.HEADER.unpack_from(data, pos)
            end = pos + size + length
            if magic != self.MAGIC or end > len(data):
                break
            payload = data[pos + size : end]
            if self._crc(length, index, payload) != crc:
                break
            out.append((pos, index, payload))
            pos = end
        if pos < len(data):
            log.warning("%s: dropping %d bytes of torn/corrupt log tail at offset %d", self.path, len(data) - pos, pos)
            self.truncate(pos)
        return out

    def append(self, index: int, payload: bytes) -> int:
        """Append one record and fsync; returns the offset it starts at (for `truncate`)."""
        offset = self._file.tell()
        self._file.write(self.HEADER.pack(self.MAGIC, len(payload), index, self._crc(len(payload), index, payload)))
        self._file.write(payload)
        self._file.flush()
        os.fsync(self._file.fileno())
        return offset

    def truncate(self, offset: int) -> None:
        self._file.flush()
        os.truncate(self.path, offset)
        self._file.seek(0, os.SEEK_END)
        os.fsync(self._file.fileno())

    def size(self) -> int:
        return self._file.tell()

    def close(self) -> None:
        self._file.close()


def configure_thread(threads: int | None) -> None:
    """Apply the ``threads`` setting in the calling thread (numba's count is per thread)."""
    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


# -- sessions ------------------------------------------------------------------------------------
@dataclass(eq=False)
class Session:
    id: str
    path: Path
    config: SceneConfig
    created: float
    scene: Scene
    log: FrameLog
    snapshot_frames: int
    lock: threading.Lock = field(default_factory=threading.Lock)
    deleted: bool = False
    dirty_since: float | None = None  # when the oldest frame not in the snapshot was folded

    # -- writing (callers hold no lock; these take it) ------------------------------------------
    def add_frame(self, payload: bytes, frame: Frame, snapshot_every_frames: int, snapshot_every_seconds: float) -> FoldReport:
        """Log (fsynced), fold, maybe snapshot. On a ValueError the log record is cut off again and the
        scene is unchanged (the library validates before it mutates)."""
        with self.lock:
            self._check_alive()
            offset = self.log.append(self.scene.frames, payload)
            try:
                report = self.scene.fold(frame)
            except ValueError:
                self.log.truncate(offset)
                raise
            except Exception:
                # not an input error: the scene may be half-folded; rebuild it from disk (without this frame)
                self.log.truncate(offset)
                try:
                    self._reload()
                except Exception:
                    log.exception("session %s: cannot be rebuilt after a failed fold; no longer serving it", self.id)
                    self.deleted = True
                raise
            now = time.monotonic()
            self.dirty_since = self.dirty_since or now
            if (self.scene.frames - self.snapshot_frames >= snapshot_every_frames
                    or now - self.dirty_since >= snapshot_every_seconds):
                self._snapshot()
            return report

    def snapshot(self) -> None:
        with self.lock:
            if not self.deleted and self.scene.frames != self.snapshot_frames:
                self._snapshot()

    def _snapshot(self) -> None:
        self.scene.save(self.path / SNAPSHOT)
        fsync_dir(self.path)
        self.log.truncate(0)  # every record is in the snapshot now
        self.snapshot_frames = self.scene.frames
        self.dirty_since = None

    def _reload(self) -> None:
        self.log.close()
        self.scene, self.log, self.snapshot_frames = restore_scene(self.path, self.config)

    def _check_alive(self) -> None:
        if self.deleted:
            raise SessionNotFound(self.id)

    # -- reading --------------------------------------------------------------------------------
    def gaussians(self, max_gaussians: int | None = None) -> tuple[Gaussians, int]:
        """Decoded Gaussians (`Scene.gaussians`: decoded once per change) and their label_dim."""
        with self.lock:
            self._check_alive()
            scene = self.scene
        g = scene.gaussians(max_gaussians)
        return g, 0 if g.labels is None else int(g.labels.shape[1])

    def summary(self) -> dict:
        return {"id": self.id, "frames": self.scene.frames, "voxels": len(self.scene), "created": self.created}

    def stats(self) -> dict:
        gaussians = len(self.gaussians()[0])  # a decode if none is cached, outside the scene's lock
        with self.lock:
            self._check_alive()
            stats = self.scene.stats()
            return {
                **self.summary(),
                "gaussians": gaussians,
                "memory_bytes": stats["memory_bytes"],
                "disk_bytes": sum(p.stat().st_size for p in self.path.iterdir() if p.is_file()),
                "label_dim": stats["label_dim"],
                "snapshot_frames": self.snapshot_frames,
                "config": self.config.to_dict(),
            }

    def digest(self) -> dict:
        """The library's digest of the fused state: equal iff the sessions fused the same frames."""
        with self.lock:
            self._check_alive()
            return {"id": self.id, "frames": self.scene.frames, "voxels": len(self.scene), "sha256": self.scene.digest()}


def restore_scene(path: Path, config: SceneConfig) -> tuple[Scene, FrameLog, int]:
    """Load the snapshot (if any) and replay the log tail. Returns (scene, open log, snapshot frames)."""
    snap = path / SNAPSHOT
    scene = Scene.load(snap) if snap.exists() else Scene(config)
    snapshot_frames = scene.frames
    frame_log = FrameLog(path / LOG)
    records = frame_log.records()
    for k, (offset, index, payload) in enumerate(records):
        if index < scene.frames:
            continue  # already in the snapshot (a crash between snapshot and log truncation)
        try:
            if index != scene.frames:
                raise ValueError(f"log: record for frame {index} follows frame {scene.frames - 1}")
            scene.fold(wire.frame_from_message(wire.unpack(payload)))
        except ValueError as exc:
            if k != len(records) - 1:
                # Records after it exist, so this one was folded and acknowledged once: never drop it
                # (e.g. a library that validates more strictly now). The session is not served.
                frame_log.close()
                raise RuntimeError(f"{path / LOG}: acknowledged frame {index} no longer folds: {exc}") from exc
            # the last record's fold failed: it was never acknowledged (the crash came before its truncation)
            log.warning("%s: dropping the unacknowledged last log record (frame %d): %s", path, index, exc)
            frame_log.truncate(offset)
    return scene, frame_log, snapshot_frames


class SessionStore:
    """All sessions of one data directory."""

    def __init__(self, data_dir: str | os.PathLike, max_sessions: int, threads: int | None = None):
        self.root = Path(data_dir) / "sessions"
        self.max_sessions = max_sessions
        self.threads = threads
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()  # guards the dict and the session count

    def open(self) -> None:
        """Load every session on disk (snapshot + log replay); clean up half-created or deleted ones."""
        configure_thread(self.threads)
        self.root.mkdir(parents=True, exist_ok=True)
        for path in sorted(self.root.iterdir()):
            if not path.is_dir():
                continue
            if path.name.startswith(TOMBSTONE):
                shutil.rmtree(path, ignore_errors=True)
                continue
            if not (path / META).is_file():
                log.warning("%s: no %s (creation never completed); removing it", path, META)
                shutil.rmtree(path, ignore_errors=True)
                continue
            t0 = time.perf_counter()
            try:
                meta = json.loads((path / META).read_text())
                config = SceneConfig.from_dict(meta["config"])
                scene, frame_log, snapshot_frames = restore_scene(path, config)
            except Exception:  # one unreadable session (e.g. a snapshot of a future version) must not stop the rest
                log.exception("%s: cannot be restored; not serving it (its files are left as they are)", path)
                continue
            self._sessions[meta["id"]] = Session(meta["id"], path, config, meta["created"], scene, frame_log, snapshot_frames)
            log.info("session %s…: %d frames (%d replayed) in %.2fs", meta["id"][:6], scene.frames,
                     scene.frames - snapshot_frames, time.perf_counter() - t0)

    def close(self) -> None:
        """Snapshot sessions with unsnapshotted frames (a faster next start) and close their logs."""
        for session in self.list():
            try:
                session.snapshot()
            finally:
                session.log.close()

    def create(self, config: SceneConfig) -> Session:
        with self._lock:
            if len(self._sessions) >= self.max_sessions:
                raise TooManySessions(f"max_sessions: the service holds {len(self._sessions)} sessions, its limit")
            session_id = secrets.token_hex(16)  # not urlsafe: an id that starts with '-' reads as a CLI flag
            path = self.root / session_id
            path.mkdir()
            created = time.time()
            frame_log = FrameLog(path / LOG)
            meta = {"format": "canonicalgs-session", "version": 1, "id": session_id, "created": created, "config": config.to_dict()}
            write_atomic(path / META, json.dumps(meta, indent=1).encode())
            session = Session(session_id, path, config, created, Scene(config), frame_log, 0)
            self._sessions[session_id] = session
            return session

    def get(self, session_id: str) -> Session:
        session = self._sessions.get(session_id)
        if session is None:
            raise SessionNotFound(session_id)
        return session

    def list(self) -> list[Session]:
        with self._lock:
            return sorted(self._sessions.values(), key=lambda s: s.created)

    def __len__(self) -> int:
        return len(self._sessions)

    def delete(self, session_id: str) -> None:
        session = self.get(session_id)
        with session.lock:
            session._check_alive()
            session.deleted = True
            session.log.close()
            with self._lock:
                self._sessions.pop(session_id, None)
            tomb = self.root / f"{TOMBSTONE}{session_id}"
            os.replace(session.path, tomb)  # atomic: a crash from here on leaves only a tombstone
            fsync_dir(self.root)
            shutil.rmtree(tomb, ignore_errors=True)

    def snapshot_due(self, every_seconds: float) -> int:
        """Snapshot sessions whose oldest unsnapshotted frame is older than ``every_seconds``."""
        now, done = time.monotonic(), 0
        for session in self.list():
            since = session.dirty_since
            if since is not None and now - since >= every_seconds:
                session.snapshot()
                done += 1
        return done

    def totals(self) -> dict:
        sessions = self.list()
        return {"sessions": len(sessions), "voxels": sum(len(s.scene) for s in sessions),
                "frames": sum(s.scene.frames for s in sessions)}


__all__ = ["FrameLog", "Session", "SessionNotFound", "SessionStore", "TooManySessions", "configure_thread"]
