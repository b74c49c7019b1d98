"""Typed dependencies shared by the routes: the settings, the store, the scheduler, the metrics, the session."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .metrics import Metrics
from .scheduler import RENDER_KINDS, Kind, Scheduler
from .session import Session
from .settings import Settings
from .store import SessionStore


# The dependencies are coroutines: FastAPI runs a plain function dependency on its threadpool (a
# thread hop per dependency and request: milliseconds each while folds keep the cores busy), and these
# only read the app's state.
async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_store(request: Request) -> SessionStore:
    return request.app.state.store


class RequestJobs:
    """The scheduler as one request uses it: its render and work jobs watch the request's client, and
    one that waits when the client has gone is dropped (`Scheduler.run`'s ``gone``): a client that gave
    up on a large render holds no place in its session's queue. A frame's jobs are not: once queued,
    its fold goes through (its retry is answered from it); a numbered frame still waiting for its turn
    is dropped by its route (`ordering.FrameOrder.wait_turn`'s ``left``)."""

    def __init__(self, scheduler: Scheduler, request: Request):
        self.scheduler, self._request = scheduler, request  # the scheduler itself for what outlives the request

    async def run(self, fn, *args, kind: Kind, **kwargs):
        gone = self._request.is_disconnected if kind in RENDER_KINDS else None
        return await self.scheduler.run(fn, *args, kind=kind, gone=gone, **kwargs)


async def get_jobs(request: Request) -> RequestJobs:
    return RequestJobs(request.app.state.jobs, request)


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[SessionStore, Depends(get_store)]
JobsDep = Annotated[RequestJobs, Depends(get_jobs)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


async def get_session(session_id: str, store: StoreDep) -> Session:
    return store.get(session_id)  # SessionNotFound -> 404


SessionDep = Annotated[Session, Depends(get_session)]
