"""The FastAPI application factory.

Run it with ``canonical serve`` or ``python -m uvicorn server.app:create_app --factory`` (settings from
``CANONICAL_*`` environment variables).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

import torch
from fastapi import FastAPI
from fastapi.concurrency import run_in_threadpool

from .warmup import warm_up

from .deps import JobQueue
from .errors import error_response, install_error_handlers
from .metrics import Metrics
from .routes import exports, frames, health, sessions, views
from .settings import Settings
from .store import DataDirLocked, SessionStore

log = logging.getLogger("canonical.server")


class GuardMiddleware:
    """Pure ASGI: refuses bodies over ``max_bytes`` (413, by Content-Length or while streaming a
    chunked body) and counts responses by status for /metrics."""

    def __init__(self, app, max_bytes: int, metrics: Metrics):
        self.app, self.max_bytes, self.metrics = app, max_bytes, metrics

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def counting_send(message):
            if message["type"] == "http.response.start":
                self.metrics.responses[message["status"]] += 1
            await send(message)

        length = dict(scope["headers"]).get(b"content-length")
        if length is not None:
            try:
                too_big = int(length) > self.max_bytes
            except ValueError:
                too_big = False
            if too_big:
                return await self._reject(scope, receive, counting_send, int(length))
            return await self.app(scope, receive, counting_send)
        if dict(scope["headers"]).get(b"transfer-encoding", b"").lower() != b"chunked":
            return await self.app(scope, receive, counting_send)
        # chunked: buffer (bounded), then hand the app the whole body
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > self.max_bytes:
                return await self._reject(scope, receive, counting_send, size, more=message.get("more_body", False))
            if not message.get("more_body", False):
                break
        body, sent = b"".join(chunks), False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        return await self.app(scope, replay, counting_send)

    async def _reject(self, scope, receive, send, size: int, more: bool = True):
        # Read (and drop) what the client is still sending, up to a bound, so that it gets to read
        # our answer instead of a reset connection; past the bound the connection is simply closed.
        budget = 4 * self.max_bytes
        while more and budget > 0:
            message = await receive()
            if message["type"] != "http.request":
                break
            budget -= len(message.get("body", b""))
            more = message.get("more_body", False)
        response = error_response(413, "too_large", f"body: {size} bytes exceed the limit of {self.max_bytes} bytes", "body")
        await response(scope, receive, send)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    store = SessionStore(settings.data_dir, settings.max_sessions, settings.threads)
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
        log.info("serving %d sessions from %s", len(store), settings.data_dir)
        snapshotter = asyncio.create_task(_snapshot_loop(store, settings.snapshot_every_seconds))
        try:
            yield
        finally:
            snapshotter.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await snapshotter
            await run_in_threadpool(store.close)

    app = FastAPI(
        title="CanonicalGS Fusion",
        version="0.1.0",
        summary="Stream posed frames into a persistent scene; render views, feature maps and Gaussian exports.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.metrics = metrics
    app.state.jobs = JobQueue(settings.queue_limit, settings.threads)
    app.add_middleware(GuardMiddleware, max_bytes=settings.max_body_bytes, metrics=metrics)
    install_error_handlers(app)
    for module in (health, sessions, frames, views, exports):
        app.include_router(module.router)
    return app


async def _snapshot_loop(store: SessionStore, every_seconds: float) -> None:
    """Snapshot sessions whose unsnapshotted frames are older than ``every_seconds`` (idle sessions too)."""
    while True:
        await asyncio.sleep(min(every_seconds, 5.0))
        try:
            await run_in_threadpool(store.snapshot_due, every_seconds)
        except Exception:  # keep the loop alive; the next fold or shutdown snapshots again
            log.exception("periodic snapshot failed")
