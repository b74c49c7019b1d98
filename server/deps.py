"""Typed dependencies shared by the routes, and the bounded job queue that runs compute off the loop."""

from __future__ import annotations

from typing import Annotated, Callable, TypeVar

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool

from .errors import ApiError
from .metrics import Metrics
from .session import Session
from .settings import Settings
from .store import SessionStore, configure_thread

T = TypeVar("T")


class JobQueue:
    """Runs compute in the threadpool; more than ``limit`` jobs running or waiting -> 429 + Retry-After.

    ``active`` is only touched on the event loop, so it needs no lock. A job that waits for a
    session's lock (folds into one session are serialised) counts as waiting.
    """

    def __init__(self, limit: int, threads: int | None, retry_after_s: int = 1):
        self.limit, self.threads, self.retry_after_s = limit, threads, retry_after_s
        self.active = 0

    async def run(self, fn: Callable[..., T], *args, **kwargs) -> T:
        if self.active >= self.limit:
            raise ApiError(429, "busy", f"queue: {self.active} jobs running or waiting, the limit is {self.limit}; retry later",
                           None, {"Retry-After": str(self.retry_after_s)})
        self.active += 1
        try:
            return await run_in_threadpool(self._call, fn, args, kwargs)
        finally:
            self.active -= 1

    def _call(self, fn, args, kwargs):
        configure_thread(self.threads)
        return fn(*args, **kwargs)


# The dependencies are coroutines: FastAPI runs a plain function dependency on its threadpool (a
# thread hop per dependency and request: milliseconds each while folds keep the cores busy), and these
# only read the app's state.
async def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_store(request: Request) -> SessionStore:
    return request.app.state.store


async def get_jobs(request: Request) -> JobQueue:
    return request.app.state.jobs


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[SessionStore, Depends(get_store)]
JobsDep = Annotated[JobQueue, Depends(get_jobs)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


async def get_session(session_id: str, store: StoreDep) -> Session:
    return store.get(session_id)  # SessionNotFound -> 404


SessionDep = Annotated[Session, Depends(get_session)]
