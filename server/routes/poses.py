"""Pose corrections and frame removal: a loop closure as one request, a frame forgotten on request."""

from __future__ import annotations

from fastapi import APIRouter

from ..deps import JobsDep, SessionDep
from ..errors import ApiError
from ..schemas import Correction, ErrorBody, PosesRequest
from ..store import CorrectionRefused, Session

router = APIRouter(prefix="/v1/sessions", tags=["poses"],
                   responses={c: {"model": ErrorBody} for c in (401, 404, 409, 422, 429, 503, 507)})


async def _correct(session: Session, jobs: JobsDep, poses: dict, remove: list) -> Correction:
    try:
        return Correction(**await jobs.run(session.correct, poses, remove))
    except CorrectionRefused as exc:
        raise ApiError(409, "correction_refused", str(exc), exc.field) from None


@router.post("/{session_id}/poses", response_model=Correction)
async def correct_poses(body: PosesRequest, session: SessionDep, jobs: JobsDep) -> Correction:
    """New poses for archived frames (one loop closure = one request), and/or frames to remove.

    The scene becomes the re-fold of the session's archived frames, in arrival order, with the new
    poses: equal (digest) to a session streamed the corrected frames. The old scene is served until
    the new one is ready; the correction is durable before it is answered. An unknown frame key, a
    pose that is not a rigid transform or holds NaN: 422 naming ``poses.<key>``; a session without a
    frame archive, or a frame folded while the correction was computed: 409. Nothing changes then."""
    return await _correct(session, jobs, dict(body.poses), list(body.remove))


@router.delete("/{session_id}/frames/{frame_id}", response_model=Correction)
async def remove_frame(frame_id: str, session: SessionDep, jobs: JobsDep) -> Correction:
    """Remove one frame (its ``frame_id``, or its arrival index): the scene becomes that of the
    session streamed without it. Errors as for ``POST .../poses``."""
    return await _correct(session, jobs, {}, [frame_id])
