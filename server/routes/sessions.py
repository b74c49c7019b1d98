"""Create, list, inspect and delete sessions."""

from __future__ import annotations

from fastapi import APIRouter

from canonical_core import SceneConfig

from ..deps import JobsDep, SessionDep, SettingsDep, StoreDep
from ..errors import ApiError
from ..schemas import (Deleted, Digest, ErrorBody, PruneReport, SessionCreate, SessionCreated, SessionList, SessionStats,
                       SessionSummary)
from ..solves import solve_soon

HTTP_MODELS = ("default", "none")  # a client must not make the service read a file of its choosing

router = APIRouter(prefix="/v1/sessions", tags=["sessions"],
                   responses={401: {"model": ErrorBody}, 404: {"model": ErrorBody}, 422: {"model": ErrorBody}})


@router.post("", status_code=201, response_model=SessionCreated, responses={409: {"model": ErrorBody}})
async def create_session(body: SessionCreate, store: StoreDep, jobs: JobsDep,  # type: ignore[valid-type]
                         service: SettingsDep) -> SessionCreated:
    """A new, empty session. Settings map onto canonical_core.SceneConfig (nested groups as objects,
    e.g. ``{"voxel_size": 0.004, "free_space": {"margin": 3}}``; without ``voxel_size`` the first frame
    with depth chooses it, and ``sensor.family`` auto the noise model: the session's GET says), and the frame
    archive's ``archive_retention`` (all, keyframes or none; default: the service's setting). A session
    that sets no ``max_voxels`` gets the service's ``max_session_voxels``, and may set no more."""
    settings = body.model_dump(exclude_unset=True)
    retention = settings.pop("archive_retention", None)
    model = settings.get("model", "default")
    if model not in HTTP_MODELS:  # before the library's check, whose message offers a checkpoint path
        raise ApiError(422, "invalid_value", f"model: 'default' or 'none' over HTTP (a client cannot make the service "
                                               f"read a file, a checkpoint included), got {model!r}", "model")
    config = SceneConfig(**settings)  # ValueError naming the field -> 422
    cap = service.max_session_voxels
    if config.max_voxels is None:
        config = config.replace(max_voxels=cap)
    elif config.max_voxels > cap:
        raise ApiError(422, "invalid_value", f"max_voxels: at most {cap} on this service (CANONICAL_MAX_SESSION_VOXELS), "
                                               f"got {config.max_voxels}", "max_voxels")
    session = await jobs.run(store.create, config, retention, kind="frame")
    return SessionCreated(id=session.id, config=session.config.to_dict(), archive_retention=session.retention)


@router.get("", response_model=SessionList)
async def list_sessions(store: StoreDep) -> SessionList:
    """Every session, those whose files need an operator (state ``unavailable``, with the problem) too."""
    summaries = [s.summary() for s in store.list()] + store.unavailable_summaries()
    return SessionList(sessions=[SessionSummary(**s) for s in summaries])


@router.post("/prune", response_model=PruneReport)
async def prune_sessions(store: StoreDep, jobs: JobsDep, service: SettingsDep,  # type: ignore[valid-type]
                         dry_run: bool = False) -> PruneReport:
    """Apply the retention policy now (what the service does every ``retention_every_s``): remove
    sessions idle longer than ``session_ttl_s``, then the oldest idle ones while the data directory
    exceeds ``disk_budget_bytes``. Never one active in the last 24 hours, nor a busy one. With
    ``?dry_run=true`` nothing is removed and the answer lists what would be."""
    return PruneReport(**await jobs.run(store.prune, service.session_ttl_s, service.disk_budget_bytes, dry_run, kind="work"))


@router.get("/{session_id}", response_model=SessionStats)
async def session_stats(session: SessionDep, jobs: JobsDep) -> SessionStats:
    """Frames, voxels, Gaussians (decodes if the cache is cold), bytes in memory and on disk. Queues
    the colour solve when one is due: a client that waits for solved colours polls this."""
    stats = SessionStats(**await jobs.run(session.stats, kind="work", session=session.id))
    solve_soon(jobs.scheduler, session)
    return stats


@router.get("/{session_id}/digest", response_model=Digest)
async def session_digest(session: SessionDep, jobs: JobsDep) -> Digest:
    """sha256 of the scene's raw sums: two sessions fused from the same frames have the same digest."""
    return Digest(**await jobs.run(session.digest, kind="work", session=session.id))


@router.delete("/{session_id}", response_model=Deleted)
async def delete_session(session_id: str, store: StoreDep, jobs: JobsDep) -> Deleted:
    """Delete the session and its files (an unavailable session's too)."""
    await jobs.run(store.delete, session_id, kind="frame", session=session_id)
    return Deleted(id=session_id)
