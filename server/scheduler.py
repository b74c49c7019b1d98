"""The service's compute: a fixed pool of worker threads that serve per-session queues, frames first.

One queue shared by every session and kind of work let ten clients looping renders on one session
fill it, so that every frame sent to another session was refused. Here each session has a queue per
kind of job, bounded on its own; the workers serve the kinds in priority order and, within a kind,
the sessions with jobs waiting in turn (round-robin), so one session's load never refuses, and hardly
delays, another session's frames. The kinds, first served first:

- ``ingest``: reading, decoding and checking a frame's body before it folds, on their own workers
  in parallel with the session's fold, so that a client keeping frames in flight has the next frame
  ready when the fold before it ends. They run at a slightly lower OS priority (``ingest_nice``):
  a decode then takes the cores the fold under way leaves, instead of one of its threads (every
  parallel kernel of a fold waits for its slowest thread), and still goes before renders.
- ``frame``: folds, pose corrections, creating and deleting sessions: the writes a streaming client
  waits on. The frame workers run them, a session's one at a time and in arrival order (its folds
  take the session lock in turn anyway: a second worker would only wait for it).
- ``work``: renders, feature and label views, exports, stats, digests, pruning.
- ``viewer``: the web viewer's pictures and session list. A picture still waiting is replaced by a
  newer one with the same ``coalesce`` key (one viewer page): the older request gets `Superseded`.
  After ``VIEWER_TURN - 1`` work jobs taken in a row while viewer jobs wait, a viewer job gets the next
  turn, so that clients looping renders slow the viewer down but never freeze it. While frames are
  held (any session's), a viewer job starts no sooner than ``VIEWER_PAUSE`` times the last one's
  duration after it ended, or when the last frame ends: a viewer following a stream (each picture
  decodes the folds since the last) then takes at most a fraction of a core from the folds, however
  many pages are open.
- ``solve``: the sessions' colour solves, in the background (`background`: no request waits for
  them). They run on their own ``solve_workers`` threads at the lowest OS priority (``solve_nice``),
  so that a solve of seconds never holds a render worker; a session's one at a time and at most one
  waiting, the sessions in turn.

Work and viewer jobs run on the render workers, whose threads (and the numba and OpenMP threads
they start, which inherit it) run at a lower OS priority (``nice``, on Linux), so that a fold
running beside a render gets the cores first. Threads and queued jobs are bounded: ``ingest_workers
+ frame_workers + render_workers + solve_workers`` threads, and at most ``queue_limit`` jobs per
session and kind.

Example:
    >>> import asyncio
    >>> scheduler = Scheduler(frame_workers=1, render_workers=1, queue_limit=2)
    >>> asyncio.run(scheduler.run(sum, [1, 2, 3], kind="frame", session="a"))
    6
    >>> scheduler.close()
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import functools
import logging
import os
import sys
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Awaitable
from dataclasses import dataclass, field
from typing import Any, Callable, Literal, TypeVar

T = TypeVar("T")
Kind = Literal["ingest", "frame", "work", "viewer", "solve"]
KINDS: tuple[Kind, ...] = ("ingest", "frame", "work", "viewer", "solve")  # priority order
FRAME_KINDS: tuple[Kind, ...] = ("ingest", "frame")  # a session's frames: being decoded, or folding
RENDER_KINDS: tuple[Kind, ...] = ("work", "viewer")  # what the render workers take, in this order
SERIAL_KINDS: tuple[Kind, ...] = ("frame", "solve")  # a session's jobs of these kinds run one at a time
# the workers' default OS priorities below the service's (the folds'): frames' decoding a little below
# the folds, renders well below the decoding, background solves the lowest there is
INGEST_NICE, RENDER_NICE, SOLVE_NICE = 5, 15, 19
VIEWER_TURN = 5  # waiting viewer jobs get at least one in this many of the render workers' jobs
VIEWER_PAUSE = 3.0  # while frames are held, the viewer's jobs take at most 1 / (1 + this) of the time
GONE_CHECK_S = 0.5  # how often a waiting request looks whether its client is still there


class QueueFull(Exception):
    """A session's queue of one kind holds ``limit`` jobs already (the service answers 429)."""

    def __init__(self, session: str, kind: Kind, limit: int):
        owner = f"session {session}" if session else "the service"
        super().__init__(f"queue_limit: {owner} has {limit} {kind} jobs running or waiting, its limit; retry later "
                         f"(other sessions and kinds of job have their own)")
        self.session, self.kind, self.limit = session, kind, limit


class Superseded(Exception):
    """A viewer job replaced, while it waited, by a newer one with the same coalesce key."""


class ClientGone(Exception):
    """The client of a request left while its job waited or ran (nobody reads the answer)."""


@dataclass(eq=False)
class _Job:
    call: Callable[[], Any]
    kind: Kind
    session: str
    coalesce: str | None
    future: asyncio.Future | None  # None: a background job, whose failure is logged
    loop: asyncio.AbstractEventLoop | None = field(repr=False)


@dataclass(eq=False)
class _Lane:
    """Workers that take ``kinds`` (in this order) at OS priority ``nice``, woken through ``ready``."""

    kinds: tuple[Kind, ...]
    workers: int
    nice: int
    ready: threading.Condition


log = logging.getLogger("canonical.scheduler")


def _settle(future: asyncio.Future, result: Any, error: BaseException | None) -> None:
    if future.done():  # its request was cancelled meanwhile
        return
    if error is None:
        future.set_result(result)
    else:
        future.set_exception(error)


class Scheduler:
    """Runs jobs on ``frame_workers`` threads (folds and the other frame jobs), ``ingest_workers`` threads
    at OS priority ``ingest_nice`` (frames' decoding), ``render_workers`` threads at ``render_nice``
    (other work, then the viewer's) and ``solve_workers`` threads at ``solve_nice`` (background
    solves); at most ``queue_limit`` jobs running or waiting per session and kind.
    ``init`` runs once in each worker thread before its first job (the service's numba thread count,
    which numba keeps per thread). Threads start with the first job.
    """

    def __init__(self, frame_workers: int, render_workers: int, queue_limit: int, render_nice: int = RENDER_NICE,
                 init: Callable[[], None] | None = None, solve_workers: int = 1, solve_nice: int = SOLVE_NICE,
                 ingest_workers: int = 1, ingest_nice: int = INGEST_NICE):
        self.limit, self._init = queue_limit, init
        self._lock = threading.Lock()
        self._lanes = (_Lane(("frame",), frame_workers, 0, threading.Condition(self._lock)),
                       _Lane(("ingest",), ingest_workers, ingest_nice, threading.Condition(self._lock)),
                       _Lane(RENDER_KINDS, render_workers, render_nice, threading.Condition(self._lock)),
                       _Lane(("solve",), solve_workers, solve_nice, threading.Condition(self._lock)))
        # kind -> session -> its waiting jobs; a session's place in the dict is its turn
        self._waiting: dict[Kind, OrderedDict[str, deque[_Job]]] = {kind: OrderedDict() for kind in KINDS}
        self._held: Counter[tuple[str, Kind]] = Counter()  # jobs running or waiting per (session, kind)
        self._serial: set[tuple[Kind, str]] = set()  # (kind, session) of the SERIAL_KINDS jobs running
        self._passed_over = 0  # work jobs taken in a row while viewer jobs waited
        self._viewer_at = 0.0  # monotonic time before which, while frames are held, no viewer job starts
        self._threads: list[threading.Thread] = []
        self._closed = False
        self.active = 0  # jobs running or waiting, all sessions and kinds
        self.superseded = 0  # viewer jobs replaced while waiting, since the start
        self.background_running = 0  # background jobs running now
        self.background_done = 0  # background jobs finished (or failed) since the start

    async def run(self, fn: Callable[..., T], *args, kind: Kind, session: str = "", coalesce: str | None = None,
                  gone: Callable[[], Awaitable[bool]] | None = None, **kwargs) -> T:
        """``fn(*args, **kwargs)`` on a worker, for ``session`` ("" for the service's own jobs).
        Raises `QueueFull` at once when the session's ``kind`` queue is full, `Superseded` when a newer
        viewer job with the same ``coalesce`` key replaced this one while it waited, `ClientGone` when
        ``gone()`` (asked every `GONE_CHECK_S`) says the requester left: a job still waiting is dropped
        then, so that a client that gave up holds no place in its session's queue."""
        loop = asyncio.get_running_loop()
        call = functools.partial(contextvars.copy_context().run, fn, *args, **kwargs)
        job = _Job(call, kind, session, coalesce, loop.create_future(), loop)
        with self._lock:
            if self._closed:
                raise RuntimeError("the scheduler is closed")
            if coalesce is not None:
                self._supersede(job)
            if self._held[session, kind] >= self.limit:
                raise QueueFull(session, kind, self.limit)
            self._held[session, kind] += 1
            self.active += 1
            self._waiting[kind].setdefault(session, deque()).append(job)
            if not self._threads:
                self._start()
            self._lane(kind).ready.notify()
        try:
            while gone is not None and not job.future.done():
                await asyncio.wait({job.future}, timeout=GONE_CHECK_S)
                if not job.future.done() and await gone():
                    raise ClientGone(session)
            return await job.future
        except (asyncio.CancelledError, ClientGone):
            with self._lock:
                self._forget(job)
            raise

    def background(self, fn: Callable[[], Any], session: str) -> bool:
        """Queue ``fn()`` as a ``solve`` job of ``session``, answered to nobody (a failure is logged),
        unless one waits already (it will see what this one would) or a frame of the session is
        running or waiting (its fold queues the next); returns whether it was queued."""
        with self._lock:
            if self._closed or self._frames_held(session) or session in self._waiting["solve"]:
                return False
            job = _Job(fn, "solve", session, None, None, None)
            self._held[session, "solve"] += 1
            self.active += 1
            self._waiting["solve"][session] = deque([job])
            if not self._threads:
                self._start()
            self._lane("solve").ready.notify()
            return True

    def frames_held(self, session: str) -> int:
        """Frame jobs of ``session`` (and frames being decoded for it) running or waiting."""
        with self._lock:
            return self._frames_held(session)

    def _frames_held(self, session: str) -> int:
        return sum(self._held[session, kind] for kind in FRAME_KINDS)

    def close(self, timeout: float = 30.0) -> None:
        """Let the workers finish the jobs taken and those a request waits for, then stop them."""
        with self._lock:
            self._closed = True
            for queue in self._waiting["solve"].values():  # nobody waits for these
                for job in queue:
                    self._release(job)
            self._waiting["solve"].clear()
            for lane in self._lanes:
                lane.ready.notify_all()
        for thread in self._threads:
            thread.join(timeout)

    def _lane(self, kind: Kind) -> _Lane:
        return next(lane for lane in self._lanes if kind in lane.kinds)

    def _start(self) -> None:
        for lane in self._lanes:
            for i in range(lane.workers):
                thread = threading.Thread(target=self._work, args=(lane,), daemon=True,
                                          name=f"canonical-{'render' if lane.kinds == RENDER_KINDS else lane.kinds[-1]}-{i}")
                thread.start()
                self._threads.append(thread)

    def _supersede(self, job: _Job) -> None:
        """Answer the waiting viewer job that ``job`` replaces (same session and key), if any."""
        queue = self._waiting[job.kind].get(job.session, ())
        for old in queue:
            if old.coalesce == job.coalesce:
                self._forget(old)
                self.superseded += 1
                _settle(old.future, None, Superseded())  # on the event loop already
                return

    def _forget(self, job: _Job) -> None:
        """Drop a job that is still waiting (one taken by a worker runs to its end)."""
        sessions = self._waiting[job.kind]
        queue = sessions.get(job.session)
        if queue is None or job not in queue:
            return
        queue.remove(job)
        if not queue:
            del sessions[job.session]
        self._release(job)

    def _release(self, job: _Job) -> None:
        self._held[job.session, job.kind] -= 1
        if not self._held[job.session, job.kind]:
            del self._held[job.session, job.kind]
        self.active -= 1
        if job.kind in FRAME_KINDS and self._waiting["viewer"]:
            self._lane("viewer").ready.notify()  # the last frame's end lifts the viewer's pause

    def _next(self, lane: _Lane) -> _Job | None:
        """The lane's next job: its first kind with a job that may run (the viewer's, when its turn
        came), the session whose turn it is."""
        kinds = lane.kinds
        pause = self._viewer_wait() if "viewer" in kinds else None
        if pause is not None and pause > 0:
            kinds = tuple(kind for kind in kinds if kind != "viewer")
        elif "viewer" in kinds and self._waiting["viewer"]:
            self._passed_over += 1
            if self._passed_over >= VIEWER_TURN or not self._waiting["work"]:
                self._passed_over, kinds = 0, ("viewer",)
        for kind in kinds:
            sessions = self._waiting[kind]
            session = next((s for s in sessions if (kind, s) not in self._serial), None)
            if session is None:
                continue
            queue = sessions[session]
            job = queue.popleft()
            if queue:
                sessions.move_to_end(session)  # the other sessions' turns come first
            else:
                del sessions[session]
            if kind in SERIAL_KINDS:
                self._serial.add((kind, session))
            self.background_running += job.future is None
            return job
        return None

    def _viewer_wait(self) -> float | None:
        """Seconds until a waiting viewer job may start, while frames are held and the pause after the
        last viewer job lasts (`VIEWER_PAUSE`): at most 0 once it may; None when no pause applies
        (no viewer job waits, or no frame is held)."""
        if not self._waiting["viewer"] or not any(kind in FRAME_KINDS for _, kind in self._held):
            return None
        return self._viewer_at - time.monotonic()

    def _work(self, lane: _Lane) -> None:
        if lane.nice and sys.platform == "linux":
            # Linux keeps the nice value per thread (elsewhere it is the whole process's: left alone);
            # the threads this one starts (numba's, OpenMP's) inherit it. Relative to the service's
            # own: a service started under `nice` keeps its renders below its folds all the same.
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + lane.nice, 19))
        if self._init is not None:
            self._init()
        while True:
            result = error = None  # an idle worker keeps nothing of its last job: an error's traceback holds its session
            with self._lock:
                while (job := self._next(lane)) is None:
                    if self._closed:
                        return
                    # until notified, or until the viewer's pause ends: a pause that ended since `_next`
                    # looked (wait <= 0) is looked at again at once, never waited on without a deadline
                    pause = self._viewer_wait() if "viewer" in lane.kinds else None
                    lane.ready.wait(None if pause is None else max(pause, 0.0))
            start = time.monotonic()
            try:
                result, error = job.call(), None
            except BaseException as exc:  # noqa: BLE001 - handed to the request that waits for it
                result, error = None, exc
            with self._lock:
                if job.kind == "viewer":
                    end = time.monotonic()
                    self._viewer_at = end + VIEWER_PAUSE * (end - start)
                self._release(job)
                if job.kind in SERIAL_KINDS:
                    self._serial.discard((job.kind, job.session))
                    lane.ready.notify()  # the session's next job of the kind may run now
                if job.future is None:
                    self.background_running -= 1
                    self.background_done += 1
            if job.future is None:
                if error is not None:
                    log.error("%s job of session %s failed", job.kind, job.session, exc_info=error)
                continue
            with contextlib.suppress(RuntimeError):  # its event loop has closed: nobody waits for the answer
                job.loop.call_soon_threadsafe(_settle, job.future, result, error)
