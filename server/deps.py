"""Typed dependencies shared by the routes: the settings, the store, the scheduler, the metrics, the session."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from .metrics import Metrics
from .scheduler import Scheduler
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


async def get_jobs(request: Request) -> Scheduler:
    return request.app.state.jobs


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[SessionStore, Depends(get_store)]
JobsDep = Annotated[Scheduler, Depends(get_jobs)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


async def get_session(session_id: str, store: StoreDep) -> Session:
    return store.get(session_id)  # SessionNotFound -> 404


SessionDep = Annotated[Session, Depends(get_session)]
