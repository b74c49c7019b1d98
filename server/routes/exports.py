"""Gaussian exports: the standard 3DGS PLY and antimatter15 .splat."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response

from canonical_core.gaussians import ply_bytes, splat_bytes

from ..deps import JobsDep, SessionDep
from ..schemas import ErrorBody

router = APIRouter(prefix="/v1/sessions", tags=["exports"],
                   responses={c: {"model": ErrorBody} for c in (401, 404, 422, 429)})

MaxGaussians = Annotated[int | None, Query(ge=0, description="level of detail: the best-supported N Gaussians")]


async def _export(session, jobs, max_gaussians, encode, suffix: str, features: bool) -> Response:
    def job():
        gaussians, _ = session.gaussians(max_gaussians, features=features)
        return encode(gaussians), len(gaussians)

    data, n = await jobs.run(job, kind="work", session=session.id)
    return Response(data, media_type="application/octet-stream", headers={
        "Content-Disposition": f'attachment; filename="{session.id}{suffix}"', "X-Canonical-Gaussians": str(n)})


@router.get("/{session_id}/gaussians.ply", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}})
async def export_ply(session: SessionDep, jobs: JobsDep, max_gaussians: MaxGaussians = None) -> Response:
    """The 3DGS PLY layout (binary little-endian float32), with feat_* / label_* extra properties."""
    return await _export(session, jobs, max_gaussians, ply_bytes, ".ply", features=True)


@router.get("/{session_id}/gaussians.splat", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}})
async def export_splat(session: SessionDep, jobs: JobsDep, max_gaussians: MaxGaussians = None) -> Response:
    """antimatter15 .splat: 32 bytes per Gaussian, most important first."""
    return await _export(session, jobs, max_gaussians, splat_bytes, ".splat", features=False)  # colour only
