"""Liveness, Prometheus metrics, and the limits a request must keep."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from ..deps import JobsDep, MetricsDep, SettingsDep, StoreDep
from ..metrics import CONTENT_TYPE
from ..schemas import ErrorBody, Health, Limits

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, response_model_exclude_none=True)
async def healthz(request: Request, store: StoreDep) -> Health:
    """Liveness (no token needed); the session count only with the token, where one is set."""
    return Health(status="ok", sessions=len(store) if request.state.authenticated else None)


@router.get("/metrics", response_class=PlainTextResponse)
async def metrics(request: Request, store: StoreDep, jobs: JobsDep, metrics: MetricsDep) -> PlainTextResponse:
    """Prometheus text format: fold/view latency histograms, frames, sessions, voxels, queue, request
    bodies and event streams."""
    totals, jobs = store.totals(), jobs.scheduler
    events = request.app.state.events
    gauges = {
        "canonical_sessions": ("Sessions held.", totals["sessions"]),
        "canonical_voxels": ("Voxels over all sessions.", totals["voxels"]),
        "canonical_frames": ("Frames folded over all sessions (including before a restart).", totals["frames"]),
        "canonical_jobs_active": ("Compute jobs running or waiting, all sessions and kinds.", jobs.active),
        "canonical_jobs_limit": ("The queue limit of each session and kind of job (one more gets 429).", jobs.limit),
        "canonical_colour_solves_running": ("Background colour solves running now.", jobs.background_running),
        "canonical_colour_solves_done_total": ("Background colour solves finished since start (solved, or nothing due).",
                                         jobs.background_done),
        "canonical_viewer_superseded_total": ("Viewer pictures replaced by a newer one while they waited, since start.",
                                        jobs.superseded),
        "canonical_sessions_unavailable": ("Sessions not served: their files need an operator (canonical repair).",
                                           totals["unavailable"]),
        "canonical_sessions_read_only": ("Sessions whose log cannot take frames until a restart.", totals["wedged"]),
        "canonical_snapshot_failures": ("Snapshots that failed since start, of the sessions held (frames stay in the log).",
                                        totals["snapshot_failures"]),
        "canonical_storage_errors_total": ("Requests refused since start because storage could not make them durable.",
                                     metrics.storage_errors),
        "canonical_request_body_bytes": ("Request body bytes received or held (max_inflight_body_bytes bounds them).",
                                         request.app.state.bodies.held),
        "canonical_memory_held_bytes": ("Memory budget held by folds under way and decoded frames waiting "
                                        "(memory_budget_bytes bounds them with the sessions' memory).",
                                        store.budget.held if store.budget is not None else 0),
        "canonical_event_streams": ("Open event streams (max_event_streams bounds them).", events.open_streams()),
        "canonical_event_streams_dropped_total": ("Event streams dropped since start for falling behind.", events.dropped),
    }
    return PlainTextResponse(metrics.exposition(gauges), media_type=CONTENT_TYPE)


@router.get("/v1/limits", response_model=Limits, responses={401: {"model": ErrorBody}})
async def limits(settings: SettingsDep) -> Limits:
    """The sizes over which a request gets 413, so that a client can fit its frames before sending them."""
    return Limits(**{name: getattr(settings, name) for name in Limits.model_fields})
