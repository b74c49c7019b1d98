"""The FastAPI application factory.

Run it with ``canonical serve`` or ``python -m uvicorn server.app:create_app --factory`` (settings from
``CANONICAL_*`` environment variables).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets

import torch
from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool

from .warmup import warm_up

from .errors import error_response, install_error_handlers
from .events import FoldEvents
from .memory import MemoryBudget, trim_heap
from .metrics import Metrics
from .routes import exports, frames, health, poses, sessions, viewer, views
from .scheduler import Scheduler
from .solves import solve_soon
from .session_errors import DataDirLocked
from .settings import Settings
from .store import SessionStore, configure_thread

log = logging.getLogger("canonical.server")
BODIES_RETRY_AFTER_S = 1  # bodies in flight are full: most are answered within a second
# seconds between looks for deleted sessions that a job held at their deletion and has let go of
DEPARTED_EVERY_S = 5.0


class BodyTimeout(Exception):
    """The request body stalled or took too long (the middleware answers 408)."""


# a large answer goes out in pieces of this size, each within send_timeout_s: small enough that a client
# reading slowly but steadily (a few kB/s) is never taken for one that reads nothing
SEND_PIECE_BYTES = 1 << 16


class ReaderStalled(Exception):
    """A client that took no bytes of its answer for ``send_timeout_s``."""


class BodiesFull(Exception):
    """A body grew past what the service's bodies in flight may hold (the middleware answers 429)."""


class BodyBytes:
    """The bytes of the request bodies being received or held, all requests together, at most ``limit``
    (``max_inflight_body_bytes``). Only touched on the event loop: no lock. Once bodies of a quarter of
    the limit were given back, glibc is asked to return the freed heap (`trim_heap`): a body arrives in
    small chunks, whose freed heap the process would otherwise keep.

    Example:
        >>> bodies = BodyBytes(100)
        >>> bodies.take(60), bodies.take(50), bodies.held
        (True, False, 60)
    """

    def __init__(self, limit: int):
        self.limit, self.held, self._freed = limit, 0, 0

    def take(self, nbytes: int) -> bool:
        if self.held + nbytes > self.limit:
            return False
        self.held += nbytes
        return True

    def give(self, nbytes: int) -> None:
        self.held -= nbytes
        self._freed += nbytes
        if self._freed >= self.limit // 4:
            self._freed = 0
            trim_heap()


class GuardMiddleware:
    """Pure ASGI, in front of every route, so that no route pays for a request it refuses:

    - the bearer token (with ``api_token`` set, everything but /healthz and the viewer's static pages
      needs it), checked from the headers before a byte of the body is read; whether the request
      carried it is ``request.state.authenticated`` (/healthz tells more to those that did);
    - the body size: 413 at once by Content-Length, or while reading a chunked body; 400 for a body
      framed both ways (Content-Length and Transfer-Encoding: a request smuggler's, RFC 9112);
    - body deadlines: 408 when the body stalls ``read_timeout_s`` between reads or is not complete
      within ``body_timeout_s``; the route then gets the whole body at once;
    - the bodies in flight, all requests together (`BodyBytes`): a body whose bytes, as they arrive,
      would pass ``max_inflight_body_bytes`` gets 429 with Retry-After; a body's bytes count until its
      request is answered. Counted as they arrive, not by Content-Length: connections that declare
      large bodies and send nothing then hold nothing, where they could take every frame's room;
    - the count of responses by status for /metrics, 500s from unhandled errors included (those
      are answered by Starlette's outermost error middleware, outside this one).
    """

    OPEN_PATHS = ("/healthz",)
    DRAIN_IDLE_S, DRAIN_TOTAL_S = 0.25, 2.0  # courtesy reads of a refused body (see _reject)

    def __init__(self, app, settings: Settings, metrics: Metrics, bodies: BodyBytes):
        self.app, self.settings, self.metrics, self.bodies = app, settings, metrics, bodies
        self.max_bytes = settings.max_body_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        started = False

        async def counting_send(message):
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                self.metrics.responses[message["status"]] += 1
            if message["type"] == "http.response.body":  # every piece, of a whole answer or a streamed one
                return await self._send_in_pieces(send, message)
            await send(message)

        try:
            await self._guarded(scope, receive, counting_send)
        except ReaderStalled as exc:  # its connection is closed: the response's bytes go back
            log.warning("%s %s: %s", scope.get("method"), scope.get("path"), exc)
        except Exception:
            if not started:  # Starlette's ServerErrorMiddleware answers 500 outside this middleware
                self.metrics.responses[500] += 1
            raise

    async def _guarded(self, scope, receive, send):
        headers = dict(scope["headers"])
        authenticated = self._authenticated(headers)
        scope.setdefault("state", {})["authenticated"] = authenticated
        if not (authenticated or self._open(scope)):
            return await self._reject(scope, receive, send, 401, "unauthorized", "Authorization: missing or wrong bearer token",
                                      "Authorization", {"WWW-Authenticate": "Bearer"})
        length = headers.get(b"content-length")
        limit, setting = self._limit(headers)
        if length is not None and b"transfer-encoding" in headers:
            return await self._reject(scope, receive, send, 400, "malformed_body", "Transfer-Encoding: given with "
                                      "Content-Length; a body is framed one way", "Transfer-Encoding")
        if length is not None:
            try:
                size = int(length)
            except ValueError:
                size = -1
            if size < 0:
                return await self._reject(scope, receive, send, 400, "malformed_body", "Content-Length: not a non-negative integer",
                                          "Content-Length")
            if size > limit:
                message = f"body: {size} bytes exceed the limit of {limit} bytes ({setting})"
                frames.body_refused(scope, message)
                return await self._reject(scope, receive, send, 413, "too_large", message, "body")
        elif headers.get(b"transfer-encoding", b"").lower() != b"chunked":
            return await self.app(scope, receive, send)
        held = [0]  # taken from the bodies in flight as it arrives
        try:
            return await self._with_body(scope, receive, send, held, limit, setting)
        finally:
            self.bodies.give(held[0])

    async def _with_body(self, scope, receive, send, held: list[int], limit: int, setting: str):
        """The body read whole (at most ``limit`` bytes: `_limit`, named by ``setting``), then the app."""
        try:
            body = await self._read_body(receive, held, limit)
        except BodyTimeout as exc:
            frames.body_refused(scope, f"body: {exc}")
            return await error_response(408, "timeout", f"body: {exc}", "body", {"Connection": "close"})(scope, receive, send)
        except BodiesFull as full:
            return await self._reject(scope, receive, send, *self._bodies_full(full.args[0]))
        if body is None:  # the client went away
            return None
        if len(body) > limit:
            message = f"body: more than {limit} bytes (the limit, {setting})"
            frames.body_refused(scope, message)
            return await self._reject(scope, receive, send, 413, "too_large", message, "body")
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, send)

    async def _send_in_pieces(self, send, message: dict) -> None:
        """A body sent a piece at a time (a large one in pieces of `SEND_PIECE_BYTES`), each within
        ``send_timeout_s``: a client that takes no bytes for that long (it never reads its answer) is
        `ReaderStalled`, so that the answer it holds in the service's memory goes back (a streamed
        export's blocks and the Gaussians behind them too), instead of staying there for as long as
        its connection does."""
        body, more = memoryview(message.get("body", b"")), message.get("more_body", False)
        timeout = self.settings.send_timeout_s
        for start in range(0, max(len(body), 1), SEND_PIECE_BYTES):
            piece = {"type": "http.response.body", "body": bytes(body[start:start + SEND_PIECE_BYTES]),
                     "more_body": more or start + SEND_PIECE_BYTES < len(body)}
            try:
                await asyncio.wait_for(send(piece), timeout)
            except TimeoutError:
                raise ReaderStalled(f"the client took no bytes of its answer for {timeout:g} s (send_timeout_s); "
                                    f"{len(body) - start} bytes unsent, its connection closed") from None

    def _limit(self, headers: dict) -> tuple[int, str]:
        """The body limit of a request and its setting's name: frames (msgpack, multipart) may take
        ``max_body_bytes``; any other body is JSON to FastAPI (it parses a body without a Content-Type
        as JSON too), parsed whole on the event loop into up to a hundred times its bytes: ``max_json_body_bytes``."""
        kind = headers.get(b"content-type", b"").partition(b";")[0].strip().lower().decode("latin-1")
        if kind in frames.FRAME_TYPES:
            return self.max_bytes, "max_body_bytes"
        return min(self.max_bytes, self.settings.max_json_body_bytes), "max_json_body_bytes"

    def _open(self, scope) -> bool:
        return scope.get("path") in self.OPEN_PATHS or viewer.is_page(scope.get("path", ""))

    def _bodies_full(self, size: int) -> tuple:
        """`_reject`'s arguments for a body that the bodies in flight cannot hold now."""
        return (429, "busy", f"body: {size} bytes would pass the {self.bodies.limit} bytes that request bodies in "
                             f"flight may hold together ({self.bodies.held} held; max_inflight_body_bytes); retry later",
                "max_inflight_body_bytes", {"Retry-After": str(BODIES_RETRY_AFTER_S)})

    def _authenticated(self, headers: dict) -> bool:
        """Whether the request carries the token (always, where none is set)."""
        token = self.settings.api_token
        if token is None:
            return True
        scheme, _, given = headers.get(b"authorization", b"").partition(b" ")
        return scheme.lower() == b"bearer" and secrets.compare_digest(given.strip(), token.get_secret_value().encode())

    async def _read_body(self, receive, held: list[int], limit: int) -> bytes | None:
        """The whole body (stopping once it passes ``limit``), or None when the client disconnected. Its
        bytes are taken from the bodies in flight as they arrive (counted in ``held[0]``), `BodiesFull`
        (with the size it would have reached) once they have no more."""
        chunks, size = [], 0
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.settings.body_timeout_s
        stalled = False
        try:
            # one timer moved before each read: a 2 MB frame arrives in dozens of chunks, and a task per
            # chunk (asyncio.wait_for) cost milliseconds of the acknowledged path
            async with asyncio.timeout(None) as timer:
                while True:
                    read_by = loop.time() + self.settings.read_timeout_s
                    stalled = read_by < deadline
                    timer.reschedule(min(read_by, deadline))
                    message = await receive()
                    if message["type"] != "http.request":
                        return None
                    chunks.append(message.get("body", b""))
                    size += len(chunks[-1])
                    if not self.bodies.take(len(chunks[-1])):
                        raise BodiesFull(size)
                    held[0] = size
                    if size > limit or not message.get("more_body", False):
                        return b"".join(chunks)
        except TimeoutError:
            raise BodyTimeout(f"no data for {self.settings.read_timeout_s:g} s" if stalled
                              else f"not complete within {self.settings.body_timeout_s:g} s") from None

    async def _reject(self, scope, receive, send, status: int, code: str, message: str, field: str, headers=None):
        # Read (and drop) what the client is still sending, briefly, so that a client that writes its
        # whole body before reading gets our answer instead of a reset connection; a client that
        # sends nothing more (or too slowly) is answered at once, and the connection is closed.
        loop = asyncio.get_running_loop()
        deadline, budget = loop.time() + self.DRAIN_TOTAL_S, 4 * self.max_bytes
        more = dict(scope["headers"]).get(b"expect", b"").lower() != b"100-continue"  # such a client waits for us
        while more and budget > 0 and loop.time() < deadline:
            try:
                event = await asyncio.wait_for(receive(), self.DRAIN_IDLE_S)
            except asyncio.TimeoutError:
                break
            if event["type"] != "http.request":
                break
            budget -= len(event.get("body", b""))
            more = event.get("more_body", False)
        await error_response(status, code, message, field, {**(headers or {}), "Connection": "close"})(scope, receive, send)


def configured(store: SessionStore, settings: Settings) -> SessionStore:
    """``store`` with the service's settings that its sessions carry: the archive's retention, how
    corrections run, the memory committed up front and the memory budget (a process's: each owner of a
    cluster has its own)."""
    store.retention = settings.archive_retention
    store.background_frames = settings.correction_background_frames
    store.undo_depth = settings.correction_undo_frames
    store.preallocate_voxels = settings.preallocate_voxels
    store.budget = MemoryBudget(settings.memory_budget_bytes, store.memory_in_use)
    return store


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    store = configured(SessionStore(settings.data_dir, settings.max_sessions, settings.threads), settings)
    metrics = Metrics()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        try:
            store.lock_dir()  # first: a second server on the directory stops here, before any work
        except DataDirLocked as exc:
            log.error("%s", exc)
            raise SystemExit(3) from None
        if settings.threads:
            torch.set_num_threads(settings.threads)
        if settings.warm_up:
            seconds = await run_in_threadpool(warm_up, settings.threads)
            log.info("kernels loaded in %.2f s", seconds)
        await run_in_threadpool(store.open)
        for session in store.list():  # restored colours are solved again (from the frames) while the service idles
            solve_soon(app.state.jobs, session)
        app.state.events.close_streams_on_exit()
        log.info("serving %d sessions from %s", len(store), settings.data_dir)
        every = settings.snapshot_every_seconds
        loops = [asyncio.create_task(_every(min(every, 5.0), "periodic snapshot", store.snapshot_due, every)),
                 asyncio.create_task(_every(DEPARTED_EVERY_S, "deleted sessions' memory", store.release_departed))]
        if settings.session_ttl_s is not None or settings.disk_budget_bytes is not None:
            loops.append(asyncio.create_task(_every(settings.retention_every_s, "retention", store.prune,
                                                    settings.session_ttl_s, settings.disk_budget_bytes)))
        try:
            yield
        finally:
            for loop in loops:
                loop.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await loop
            await run_in_threadpool(app.state.jobs.close)
            await run_in_threadpool(store.close)

    app = FastAPI(
        title="CanonicalGS Fusion",
        version="0.1.0",
        summary="Stream posed frames into a persistent scene; render views, feature maps and Gaussian exports.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.frame_refused = store.frame_refused  # a cluster's ingress tells the session's owner instead
    app.state.metrics = metrics
    app.state.jobs = Scheduler(settings.frame_workers, settings.render_workers, settings.queue_limit, settings.render_nice,
                               init=lambda: configure_thread(settings.threads), solve_workers=settings.solve_workers,
                               solve_nice=settings.solve_nice, ingest_workers=settings.ingest_workers,
                               ingest_nice=settings.ingest_nice)
    app.state.events = FoldEvents(settings.max_event_streams_per_session, settings.max_event_streams)
    app.state.bodies = BodyBytes(settings.max_inflight_body_bytes)
    app.add_middleware(GuardMiddleware, settings=settings, metrics=metrics, bodies=app.state.bodies)
    install_error_handlers(app)
    for module in (health, sessions, frames, poses, views, exports, viewer):
        app.include_router(module.router)
    app.include_router(viewer.info_router)
    app.include_router(viewer.pages)
    return app


async def _every(seconds: float, what: str, job, *args) -> None:
    """Run ``job(*args)`` off the event loop every ``seconds``: the periodic snapshot (sessions whose
    unsnapshotted frames are older than its setting, idle ones too), the memory of deleted sessions
    that jobs held at their deletion, and retention."""
    while True:
        await asyncio.sleep(seconds)
        try:
            await run_in_threadpool(job, *args)
        except Exception:  # keep the loop alive; the next round tries again
            log.exception("%s failed", what)
