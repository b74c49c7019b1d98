"""The cluster's HTTP front: the service's own FastAPI app (auth, body limits, errors, 404/405) with one
more middleware inside its guard that forwards each session's requests to the session's owner.

- ``/v1/sessions/{id}[/...]``: to owner ``shard_of(id)``, which runs it through the same app.
- ``POST /v1/sessions``: to an owner picked at random, which makes an id that hashes to itself.
- ``GET /v1/sessions``, ``GET /metrics``, ``GET /healthz``: gathered from every owner / the data dir
  (``/healthz`` without the token, where one is set, is the app's own: liveness alone).

A request whose owner cannot be reached (its process died and is being restarted, or it is slow) is
answered 429 ``busy`` with ``Retry-After``, once the owner answers again (or after
``owner_restart_wait_s``): nothing of it was acknowledged, and clients retry 429. A request is sent only
to an owner this replica knows to run: one not seen running yet, or lost since, is asked for its pid
first, and one that does not answer within ``owner_restart_wait_s`` (still starting, or waiting for CPUs
Ray cannot give it) gets the 429 then, its request never sent, rather than after ``owner_timeout_s``.
Ingress replicas hold no state, so Serve can add and remove them at will.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
from typing import Protocol

from fastapi import FastAPI
from fastapi.encoders import jsonable_encoder
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from starlette.middleware import Middleware

from ..app import create_app
from ..errors import error_response
from ..metrics import CONTENT_TYPE
from ..schemas import Health, SessionList, SessionSummary
from .asgi import read_body, send_response
from .lease import sessions_on_disk
from .metrics import exposition
from .owner import session_of, shard_of
from .settings import ClusterSettings

log = logging.getLogger("canonical.cluster")


class OwnerUnreachable(RuntimeError):
    """The owner's process is gone (being restarted) or did not answer in time."""


class Owners(Protocol):
    """The session owners, by shard: `server.cluster.serve.RayOwners` (actors) or `LocalOwners`."""

    count: int

    async def call(self, shard: int, method: str, *args): ...


class LocalOwners:
    """Owners in this process (`SessionOwner` objects): the cluster's routing without Ray."""

    def __init__(self, owners: list):
        self.owners, self.count = owners, len(owners)

    async def call(self, shard: int, method: str, *args):
        result = getattr(self.owners[shard], method)(*args)
        return await result if asyncio.iscoroutine(result) else result


def owner_busy(reason: str):
    return error_response(429, "busy", f"session_id: {reason}; retry later", "session_id", {"Retry-After": "1"})


class ClusterRouter:
    """Pure ASGI, inside the app's guard (so auth and body limits are checked first), in front of its routes."""

    def __init__(self, app, settings: ClusterSettings, owners: Owners):
        self.app, self.settings, self.owners = app, settings, owners
        self._running: set[int] = set()  # shards whose owner answered since it was last lost

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        path, method = scope["path"], scope["method"]
        session_id = session_of(path)
        if session_id is not None and path.endswith("/events"):
            # an owner answers a forwarded request as one whole response; a live event stream is not one
            return await error_response(501, "not_implemented", "path: live fold events are served by the "
                                        "single-process service only; poll GET /v1/sessions/{id} in cluster mode",
                                        "path")(scope, receive, send)
        if path == "/v1/sessions/prune":  # not a session: owners hold some sessions each, the directory is shared
            return await error_response(501, "not_implemented", "path: retention (session_ttl_s, disk_budget_bytes) "
                                        "is applied by the single-process service only", "path")(scope, receive, send)
        if session_id is not None:
            shard = shard_of(session_id, self.owners.count)
        elif path == "/v1/sessions" and method == "POST":  # max_sessions: the owner counts, creates in turn (`one_creator`)
            shard = secrets.randbelow(self.owners.count)
        elif method == "GET" and path == "/healthz" and not scope["state"]["authenticated"]:
            return await self.app(scope, receive, send)  # liveness alone: the count is for the token's holders
        elif method == "GET" and path in ("/v1/sessions", "/metrics", "/healthz"):
            return await (await self._gathered(path))(scope, receive, send)
        elif method == "GET" and path == "/v1/viewer/sessions":
            return await (await self._viewer_sessions(scope["headers"]))(scope, receive, send)
        else:
            return await self.app(scope, receive, send)
        body = await read_body(receive)
        if body is None:
            return None
        try:
            status, headers, content = await self._call(shard, "handle", method, path, scope["query_string"],
                                                        scope["headers"], body)
        except OwnerUnreachable as exc:
            return await owner_busy(str(exc))(scope, receive, send)
        await send_response(send, status, headers, content)

    async def _until_back(self, shard: int) -> bool:
        """Wait (at most ``owner_restart_wait_s``) until owner ``shard`` answers (Ray starts or restarts
        it); whether it did."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.settings.owner_restart_wait_s
        while True:
            try:
                await asyncio.wait_for(self.owners.call(shard, "pid"), max(0.1, deadline - loop.time()))
                self._running.add(shard)
                return True
            except (OwnerUnreachable, asyncio.TimeoutError):
                if loop.time() >= deadline:
                    return False
                await asyncio.sleep(0.25)

    async def _call(self, shard: int, method: str, *args):
        """``method`` of owner ``shard``; `OwnerUnreachable` when the owner is not running or does not
        answer (the client retries: a frame it sends again is recognised by its ``frame_id``)."""
        wait = self.settings.owner_restart_wait_s
        if shard not in self._running and not await self._until_back(shard):
            # a call to an actor that is not running waits in Ray's queue for as long as it takes to place it
            raise OwnerUnreachable(f"owner {shard} is not running (starting, restarting, or waiting for CPUs) "
                                   f"after {wait:g} s (owner_restart_wait_s)")
        try:
            return await asyncio.wait_for(self.owners.call(shard, method, *args), self.settings.owner_timeout_s)
        except asyncio.TimeoutError:
            raise OwnerUnreachable(f"owner {shard} did not answer within {self.settings.owner_timeout_s:g} s") from None
        except OwnerUnreachable:
            self._running.discard(shard)
            await self._until_back(shard)  # so that the client's retry finds the owner running
            raise

    async def _gathered(self, path: str):
        if path == "/healthz":
            return JSONResponse(Health(status="ok", sessions=await asyncio.to_thread(sessions_on_disk, self.settings.data_dir)).model_dump())
        method = "summaries" if path == "/v1/sessions" else "report"
        answers = await asyncio.gather(*(self._call(k, method) for k in range(self.owners.count)), return_exceptions=True)
        failed = [a for a in answers if isinstance(a, BaseException)]
        for exc in failed:
            if not isinstance(exc, OwnerUnreachable):
                raise exc
        if path == "/metrics":
            reports = [a for a in answers if not isinstance(a, BaseException)]
            text = exposition(reports, await asyncio.to_thread(sessions_on_disk, self.settings.data_dir), len(failed))
            return PlainTextResponse(text, media_type=CONTENT_TYPE)
        if failed:
            return owner_busy(str(failed[0]))
        held = sorted((s for a in answers for s in a[0]), key=lambda s: s["created"])
        unavailable = sorted((s for a in answers for s in a[1]), key=lambda s: s["id"])
        return JSONResponse(jsonable_encoder(SessionList(sessions=[SessionSummary(**s) for s in held + unavailable])))

    async def _viewer_sessions(self, headers: list):
        """The web viewer's session list: each owner's (its sessions' stats and last folds), merged as
        the single-process service orders them (served by creation, then the unavailable ones)."""
        answers = await asyncio.gather(*(self._call(k, "handle", "GET", "/v1/viewer/sessions", b"", headers, b"")
                                         for k in range(self.owners.count)), return_exceptions=True)
        rows = []
        for answer in answers:
            if isinstance(answer, OwnerUnreachable):
                return owner_busy(str(answer))
            if isinstance(answer, BaseException):
                raise answer
            status, _, content = answer
            if status != 200:  # the owner's own refusal (401 ...): as it is
                return Response(content, status_code=status, media_type="application/json")
            rows += json.loads(content)["sessions"]
        served = [s for s in rows if s["state"] != "unavailable"]
        unavailable = [s for s in rows if s["state"] == "unavailable"]
        return JSONResponse({"sessions": sorted(served, key=lambda s: s["created"])
                             + sorted(unavailable, key=lambda s: s["id"])})


@contextlib.asynccontextmanager
async def _stateless(app: FastAPI):
    yield  # the ingress opens no store: the owners hold the sessions


def ingress_app(settings: ClusterSettings, owners: Owners) -> FastAPI:
    """The service's app, routing session requests to ``owners``."""
    app = create_app(settings)
    app.router.lifespan_context = _stateless
    app.user_middleware.append(Middleware(ClusterRouter, settings=settings, owners=owners))  # innermost: after the guard
    app.state.frame_refused = RefusalsToOwners(owners)
    return app


class RefusalsToOwners:
    """`frames.body_refused` in the ingress: a numbered frame whose body the guard refused is told to
    its session's owner, where the frames numbered after it wait (they are then refused at once,
    naming it, instead of waiting for it in vain); sent off the guard's path, a lost owner logged."""

    def __init__(self, owners: Owners):
        self.owners, self.sending = owners, set()

    def __call__(self, session_id: str, index: int, why: str) -> None:
        task = asyncio.get_running_loop().create_task(self._send(session_id, index, why))
        self.sending.add(task)  # held until done: the loop keeps only weak references to tasks
        task.add_done_callback(self.sending.discard)

    async def _send(self, session_id: str, index: int, why: str) -> None:
        try:
            await self.owners.call(shard_of(session_id, self.owners.count), "frame_refused", session_id, index, why)
        except Exception as exc:  # noqa: BLE001 - the owner is gone: its restart holds no waiting frames
            log.warning("session %s: frame %d refused at the ingress, its owner not told (%s)", session_id, index, exc)


__all__ = ["ClusterRouter", "LocalOwners", "OwnerUnreachable", "Owners", "RefusalsToOwners", "ingress_app"]
