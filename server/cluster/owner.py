"""A session owner: one process that holds a shard of the sessions in memory and answers their requests
through the service's own FastAPI app. No Ray here (`server.cluster.serve` runs it as a Ray actor), so
it can be used and tested in-process.

- Ownership is explicit: session ``id`` belongs to owner ``shard_of(id, owners)``; an owner creates
  only ids that hash to itself. Before it reads a session's folder it takes the session's `Lease`, so
  a previous owner that still runs cannot write to it any more.
- Sessions are restored lazily: on their first request after a start, or after an eviction.
- Idle sessions are evicted (snapshot, then drop) least recently used first while the scenes held
  (``Scene.memory_bytes``) exceed the owner's memory budget; never one with a request in flight, and
  a request during an eviction restores the session after it (the lease serialises the two).
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import os
import re
import secrets
import socket
import threading
import time
from collections import Counter, OrderedDict

import torch

from canonical_core import SceneConfig

from ..app import configured, create_app
from ..archive import Retention
from ..durability import restore_session, session_meta
from ..framelog import Fenced
from ..memory import release_memory
from ..metrics import Histogram
from ..session import Session
from ..session_errors import SessionNotFound, SessionUnavailable, Unrestorable
from ..snapshots import Snapshots
from ..store import META, SessionStore, configure_thread
from ..warmup import warm_up
from .asgi import call_app
from .lease import Lease, one_creator
from .settings import ClusterSettings

log = logging.getLogger("canonical.cluster")

SESSION_ID = re.compile(r"^[0-9a-f]{32}$")  # what `SessionStore.new_session_id` makes
SESSION_PATH = re.compile(r"^/v1/sessions/([^/]+)(/.*)?$")


def shard_of(session_id: str, owners: int) -> int:
    """The owner (0 .. owners - 1) of a session id: a stable hash, the same in every process."""
    return int.from_bytes(hashlib.blake2b(session_id.encode(), digest_size=8).digest(), "little") % owners


def session_of(path: str) -> str | None:
    """The session id a request path names (``/v1/sessions/{id}`` and below), or None."""
    match = SESSION_PATH.match(path)
    return match.group(1) if match else None


def _log_failure(task: asyncio.Task) -> None:
    if not task.cancelled() and task.exception() is not None:
        log.error("eviction failed: %r", task.exception())


RATE_WINDOW_S = 10.0  # the folds/s figure of /metrics: over the last whole window this long


class FencedSnapshots(Snapshots):
    """The snapshots of an `OwnedSession`: a snapshot holds the lease over both its files, and a fenced
    one marks the session ``stale``."""

    # a snapshot and the log's restart hold the lease as one step: they stay on the caller's path here
    write_off_path = False

    def take(self) -> None:
        session = self.session
        if session.archive is not None:  # before the lease is held: the archive's writer takes it for each append
            session.archive.flush()
        try:
            with session.log.fenced():  # the snapshot and the log's restart are one step for other owners
                super().take()
        except Fenced as exc:
            session.stale = True
            log.warning("session %s: not snapshotted: %s", session.id, exc)


class OwnedSession(Session):
    """A `Session` whose log writes are fenced by its lease (``log.lease``): a snapshot holds the lease
    over both its files, and a fenced write marks the session ``stale`` (its owner drops it and reads
    it again from disk on the next request)."""

    stale = False
    snapshots_class = FencedSnapshots

    def add_frame(self, *args, **kwargs):
        try:
            return super().add_frame(*args, **kwargs)
        except Fenced:
            self.stale = True
            raise

    def _reload(self) -> None:
        lease = self.log.lease
        super()._reload()
        self.log.lease = lease

    def fence(self, lease: Lease) -> None:
        """Fence every append of this owner (the frame log's and the frame archive's) by ``lease``."""
        self.log.lease = lease
        if self.archive is not None:
            self.archive.fence(lease)

    def release(self) -> None:
        """Close the log and the lease (after an eviction or a deletion)."""
        self.log.close()
        if self.log.lease is not None:
            self.log.lease.close()


class OwnerStore(SessionStore):
    """The sessions of one owner: shard ``shard`` of ``owners`` in a data directory shared with the
    other owners (so it takes no directory lock: every session folder has its lease instead)."""

    session_class = OwnedSession

    def __init__(self, data_dir, max_sessions: int, threads: int | None, shard: int, owners: int):
        super().__init__(data_dir, max_sessions, threads)
        self.shard, self.owners = shard, owners
        self._loading = threading.Lock()  # one restore at a time: two would fence each other
        self.used: OrderedDict[str, None] = OrderedDict()  # least recently used first
        self.evicted: dict[str, dict] = {}  # summaries of the sessions evicted since they were last held
        self.restores = self.evictions = 0
        self.restore_seconds = Histogram()

    def lock_dir(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)

    def open(self) -> None:
        """Sessions are restored on their first request, not at start."""
        configure_thread(self.threads)
        self.lock_dir()

    def new_session_id(self) -> str:
        while True:
            session_id = super().new_session_id()
            if shard_of(session_id, self.owners) == self.shard:
                return session_id

    def create(self, config: SceneConfig, retention: Retention | None = None) -> Session:
        with one_creator(self.data_dir, self.max_sessions):  # max_sessions is the directory's, not an owner's
            session = super().create(config, retention)
        lease = Lease(session.path)
        with lease.take():
            session.fence(lease)
        self.touch(session.id)
        return session

    def get(self, session_id: str) -> Session:
        with self._lock:  # an eviction removes a session under this lock once it saw no request pinning it
            session = self._sessions.get(session_id)
        if session is not None and not session.stale:
            return session
        with self._loading:
            session = self._sessions.get(session_id)
            if session is None or session.stale:
                session = self._restore(session_id)
        return session

    def _restore(self, session_id: str) -> Session:
        stale = self._sessions.get(session_id)
        if stale is not None:
            self._drop(stale)
        if session_id in self.unavailable:
            raise SessionUnavailable(session_id, self.unavailable[session_id])
        path = self.root / session_id
        if not SESSION_ID.match(session_id) or not (path / META).is_file():
            raise SessionNotFound(session_id)
        t0 = time.perf_counter()
        lease = Lease(path)
        try:
            with lease.take():
                meta, config = session_meta(path)
                restored, archive = restore_session(path, config, meta.get("archive_retention", "all"),
                                                     meta.get("chosen"))
        except Unrestorable as exc:
            lease.close()
            self._unavailable(session_id, str(exc))
            raise SessionUnavailable(session_id, str(exc)) from None
        except BaseException:
            lease.close()
            raise
        session = OwnedSession(meta["id"], path, config, meta["created"], *restored, archive=archive,
                               chosen=meta.get("chosen", {}), **self._session_options())
        session.fence(lease)
        with self._lock:
            self._sessions[session_id] = session
        self.evicted.pop(session_id, None)
        self.restores += 1
        self.restore_seconds.observe(time.perf_counter() - t0)
        log.info("session %s…: restored %d frames in %.2fs", session_id[:6], session.scene.frames, time.perf_counter() - t0)
        return session

    def _drop(self, session: OwnedSession) -> None:
        with self._lock:
            if self._sessions.get(session.id) is session:
                del self._sessions[session.id]
        with session.lock:
            session.deleted = True  # any straggler holding the object gets 404 instead of writing
            session.release()

    def touch(self, session_id: str) -> None:
        self.used[session_id] = None
        self.used.move_to_end(session_id)

    def memory_bytes(self) -> int:
        return sum(s.scene.memory_bytes() for s in self.list())

    def evict(self, budget: int, busy) -> list[str]:
        """Evict idle sessions (not in ``busy``), least recently used first, until the scenes held fit
        in ``budget`` bytes. Each is snapshotted first (under its lease), so its restore replays nothing."""
        held = {s.id: s for s in self.list()}
        total = sum(s.scene.memory_bytes() for s in held.values())
        done = []
        order = list(self.used)  # one step under the GIL: the event loop touches it meanwhile
        for session_id in [i for i in order if i in held] + [i for i in held if i not in order]:
            if total <= budget:
                break
            session = held[session_id]
            with self._lock:
                # a request pins its session before it looks it up (`get`, under this lock): either it
                # is pinned now and the session stays, or its lookup comes after this and restores it
                if session_id in busy or self._sessions.get(session_id) is not session:
                    continue
                del self._sessions[session_id]
            total -= session.scene.memory_bytes()
            session.snapshot()
            self.evicted[session_id] = {**session.summary(), "memory_bytes": 0}  # on disk alone until asked for
            with session.lock:
                session.deleted = True
                session.release()
            self.used.pop(session_id, None)
            self.evictions += 1
            done.append(session_id)
        if done:
            held.clear()  # this function's last references to the evicted sessions, then their memory goes back
            session = None
            release_memory()
        return done

    def delete(self, session_id: str) -> None:
        session = None if session_id in self.unavailable else self.get(session_id)  # restored if evicted
        super().delete(session_id)
        self.evicted.pop(session_id, None)
        self.used.pop(session_id, None)
        if isinstance(session, OwnedSession) and session.log.lease is not None:
            session.log.lease.close()
        session = None  # this function's reference: the delete found the session held by it
        self.release_departed()

    def mine(self) -> list[str]:
        """Ids of the sessions on disk that belong to this owner."""
        if not self.root.is_dir():
            return []
        return sorted(p.name for p in self.root.iterdir()
                      if SESSION_ID.match(p.name) and shard_of(p.name, self.owners) == self.shard)

    def summaries(self) -> tuple[list[dict], list[dict]]:
        """(summaries of this owner's sessions, of its unavailable ones), as `GET /v1/sessions` lists
        them; a session neither held nor evicted since this owner started is restored to be listed."""
        for session_id in self.mine():
            if session_id not in self._sessions and session_id not in self.evicted and session_id not in self.unavailable:
                try:
                    self.get(session_id)
                except (SessionNotFound, SessionUnavailable):
                    pass
        held = [s.summary() for s in self.list()]
        listed = {s["id"] for s in held}
        return held + [s for i, s in self.evicted.items() if i not in listed], self.unavailable_summaries()


# the answer of an owner that is stopping, as the single-process service answers then: try again soon
STOPPING = (503, [(b"content-type", b"application/json"), (b"retry-after", b"5")], json.dumps(
    {"error": {"code": "unavailable", "message": "the service is stopping; send the request again once it is back",
               "field": None}}).encode())


class SessionOwner:
    """Shard ``shard`` of ``settings.owners``: an `OwnerStore` behind the service's FastAPI app, answering
    forwarded requests (`handle`) exactly as the single-process service does."""

    def __init__(self, settings: ClusterSettings, shard: int):
        self.settings, self.shard = settings, shard
        if settings.threads:
            torch.set_num_threads(settings.threads)
        if settings.warm_up:
            warm_up(settings.threads)
        self.store = configured(OwnerStore(settings.data_dir, settings.max_sessions, settings.threads, shard,
                                           settings.owners), settings)
        self.store.open()
        self.app = create_app(settings)
        self.app.state.store = self.store  # the app's lifespan does not run here: this object is its life
        self.app.state.frame_refused = self.store.frame_refused
        self.busy: Counter[str] = Counter()
        self._evicting: asyncio.Task | None = None
        self._snapshotter: asyncio.Task | None = None
        # (when, frames, folds/s) at the last window's start: the rate over whole windows of RATE_WINDOW_S,
        # so that it does not depend on how often, or by how many, /metrics is read
        self._rate = (time.monotonic(), 0, 0.0)
        self.node = os.environ.get("CANONICAL_NODE") or socket.gethostname()
        self.closed = False

    def frame_refused(self, session_id: str, index: int, why: str) -> None:
        """Numbered frame ``index`` of a held session was refused at the ingress (`SessionStore.frame_refused`)."""
        self.store.frame_refused(session_id, index, why)

    async def handle(self, method: str, path: str, query: bytes, headers: list, body: bytes) -> tuple[int, list, bytes]:
        """One HTTP request through the app: (status, headers, body); 503 once the owner is closed."""
        if self.closed:
            return STOPPING
        if self._snapshotter is None:
            self._snapshotter = asyncio.create_task(self._snapshot_loop())
        session_id = session_of(path)
        if session_id is not None:
            self.busy[session_id] += 1
        try:
            return await call_app(self.app, method, path, query, headers, body)
        finally:
            if session_id is not None:
                self.busy[session_id] -= 1
                if not self.busy[session_id]:
                    del self.busy[session_id]
                if session_id in self.store._sessions:
                    self.store.touch(session_id)
            self._maybe_evict()

    def _maybe_evict(self) -> None:
        budget = self.settings.owner_memory_bytes
        if budget is None or (self._evicting is not None and not self._evicting.done()):
            return
        self._evicting = asyncio.create_task(asyncio.to_thread(self.store.evict, budget, self.busy))
        self._evicting.add_done_callback(_log_failure)

    async def evict(self, budget: int) -> list[str]:
        """Evict idle sessions down to ``budget`` bytes now (operators, tests)."""
        return await asyncio.to_thread(self.store.evict, budget, self.busy)

    async def _snapshot_loop(self) -> None:
        every = self.settings.snapshot_every_seconds
        while True:
            await asyncio.sleep(min(every, 5.0))
            try:
                await asyncio.to_thread(self.store.snapshot_due, every)
                await asyncio.to_thread(self.store.release_departed)  # deleted sessions a job held meanwhile
            except Exception:  # keep the loop alive; the next fold or eviction snapshots again
                log.exception("periodic snapshot failed")

    async def summaries(self) -> tuple[list[dict], list[dict]]:
        return await asyncio.to_thread(self.store.summaries)

    def report(self) -> dict:
        """This owner's figures for the cluster's /metrics (`server.cluster.metrics.exposition`)."""
        m, now = self.app.state.metrics, time.monotonic()
        then, frames, rate = self._rate
        if now - then >= RATE_WINDOW_S:
            rate = (m.frames_total - frames) / (now - then)
            self._rate = (now, m.frames_total, rate)
        totals = self.store.totals()
        return {
            "node": self.node, "owner": self.shard, "pid": os.getpid(),
            "fold": (m.fold_seconds.counts, m.fold_seconds.sum),
            "view": {k: (h.counts, h.sum) for k, h in m.view_seconds.items()},
            "restore": (self.store.restore_seconds.counts, self.store.restore_seconds.sum),
            "frames_total": m.frames_total, "responses": dict(m.responses), "storage_errors": m.storage_errors,
            "folds_per_second": rate,
            "sessions": totals["sessions"], "voxels": totals["voxels"], "frames": totals["frames"],
            "unavailable": totals["unavailable"], "wedged": totals["wedged"], "snapshot_failures": totals["snapshot_failures"],
            "memory_bytes": self.store.memory_bytes(), "restores": self.store.restores, "evictions": self.store.evictions,
            "jobs_active": self.app.state.jobs.active, "jobs_limit": self.app.state.jobs.limit,
            "solves_running": self.app.state.jobs.background_running, "solves_done": self.app.state.jobs.background_done,
            "superseded": self.app.state.jobs.superseded,
        }

    def pid(self) -> int:
        return os.getpid()

    def settings_json(self) -> str:
        """The settings this owner runs with: a service that starts with others replaces it."""
        return self.settings.model_dump_json()

    async def close(self) -> None:
        """Snapshot the sessions held and close their files (a graceful stop); requests that still
        come are answered 503 (`handle`), not folded into closed files."""
        self.closed = True
        if self._snapshotter is not None:
            self._snapshotter.cancel()
        await asyncio.to_thread(self.store.close)
