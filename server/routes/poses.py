"""Pose corrections and frame removal: a loop closure as one request, a frame forgotten on request."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from starlette.convertors import Convertor, register_url_convertor

from ..deps import JobsDep, SessionDep
from ..errors import ApiError
from ..schemas import Correction, CorrectionStatus, ErrorBody, PosesRequest
from ..session import Session
from ..session_errors import CorrectionRefused
from ..solves import solve_soon

router = APIRouter(prefix="/v1/sessions", tags=["poses"],
                   responses={c: {"model": ErrorBody} for c in (401, 404, 409, 422, 429, 503, 507)})


async def _correct(session: Session, jobs: JobsDep, poses: dict, remove: list, wait: bool = True):
    try:
        done = await jobs.run(session.corrections.correct, poses, remove, wait, kind="frame", session=session.id)
    except CorrectionRefused as exc:
        raise ApiError(409, "correction_refused", str(exc), exc.field) from None
    if done["state"] == "done":
        solve_soon(jobs.scheduler, session)  # the corrected scene's colours (a background one's: at the next stats read)
        return Correction(**done)
    # its status as accepted ("pending"), not as its re-fold may have begun since: GET .../corrections/{id}
    return JSONResponse(CorrectionStatus(**done["status"]).model_dump(), status_code=202)


@router.post("/{session_id}/poses", response_model=Correction, responses={202: {"model": CorrectionStatus}})
async def correct_poses(body: PosesRequest, session: SessionDep, jobs: JobsDep):
    """New poses for archived frames (one loop closure = one request), and/or frames to remove.

    The scene becomes the re-fold of the session's archived frames, in arrival order, with the new
    poses: equal (digest) to a session streamed the corrected frames. A correction of recent frames
    re-folds only them and answers 200 when done. A long one (or any with ``"wait": false``) is
    archived, answered 202 with its status (``state`` pending, a ``correction_id``), and re-folds in
    the background: the old scene is served and takes frames meanwhile, which the re-fold catches up
    on before it swaps the corrected scene in; ``GET .../corrections/{correction_id}`` tells its
    progress. The correction is durable before it is answered. ``poses_by_arrival`` and the integers
    of ``remove`` name frames by arrival index only. An unknown frame key, a pose that is
    not a rigid transform or holds NaN: 422 naming ``poses.<key>`` (``frames.<key>`` for removals);
    a session without a frame archive, a frame folded while a short correction was computed, or a
    correction while a background one runs: 409. Nothing changes then."""
    return await _correct(session, jobs, {**body.poses, **body.poses_by_arrival}, list(body.remove), body.wait)


class _AnyText(Convertor[str]):
    """A path parameter of any characters: '/' (sent as is or as %2F), which a plain parameter stops
    at, and line breaks, which Starlette's ``path`` does not match."""

    regex = r"[\s\S]*"

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("any_text", _AnyText())


@router.delete("/{session_id}/frames/{frame_id:any_text}", response_model=Correction,
               responses={202: {"model": CorrectionStatus}})
async def remove_frame(frame_id: str, session: SessionDep, jobs: JobsDep):
    """Remove one frame (its ``frame_id``, any characters, percent-encoded; or its arrival index):
    the scene becomes that of the session streamed without it. Answers and errors as for
    ``POST .../poses``."""
    return await _correct(session, jobs, {}, [frame_id])


@router.get("/{session_id}/corrections/{correction_id}", response_model=CorrectionStatus)
async def correction_status(correction_id: str, session: SessionDep) -> CorrectionStatus:
    """A background correction's state (pending, running, done, failed) and progress (frames
    re-folded of the total); once done, what it did. 404 naming ``correction_id`` for an unknown id."""
    try:
        return CorrectionStatus(**session.corrections.status(correction_id))
    except KeyError:
        raise ApiError(404, "not_found", f"correction_id: no correction {correction_id!r} in this session",
                       "correction_id") from None
