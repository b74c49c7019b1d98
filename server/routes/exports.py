"""Exports: the Gaussians (the standard 3DGS PLY, antimatter15 .splat) and the surface as a triangle mesh (PLY)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response, StreamingResponse

from canonical_core.gaussians import ply_file, splat_file
from canonical_core.scene.mesh import mesh_ply_bytes

from ..deps import JobsDep, SessionDep
from ..errors import ApiError
from ..schemas import ErrorBody
from ..solves import solve_soon

router = APIRouter(prefix="/v1/sessions", tags=["exports"],
                   responses={c: {"model": ErrorBody} for c in (401, 404, 422, 429)})

MinSupport = Annotated[float, Query(ge=0, allow_inf_nan=False, description="R_scene a voxel needs to count as surface")]
MaxGaussians = Annotated[int | None, Query(ge=0, description="level of detail: the best-supported N Gaussians")]


async def _export(session, jobs, max_gaussians, encode, suffix: str, features: bool) -> StreamingResponse:
    """The decode and what the file needs of all the Gaussians at once (their check, a .splat's order)
    are a job of the session's; the file is then encoded a block of rows at a time as the client takes
    it (on the server's thread pool: `StreamingResponse` runs a plain iterator there), so a scene of
    millions of Gaussians never holds its whole file in memory. The decoded Gaussians are not changed
    by later folds (a fold makes new ones), so the file is of one state."""
    def job():
        gaussians, _ = session.gaussians(max_gaussians, features=features)
        return encode(gaussians), len(gaussians)

    file, n = await jobs.run(job, kind="work", session=session.id)
    solve_soon(jobs.scheduler, session)  # as a render does: a session whose colours are due gets them solved
    return StreamingResponse(file.chunks, media_type="application/octet-stream", headers={
        "Content-Length": str(file.size), "Content-Disposition": f'attachment; filename="{session.id}{suffix}"',
        "X-Canonical-Gaussians": str(n)})


@router.get("/{session_id}/gaussians.ply", response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}}})
async def export_ply(session: SessionDep, jobs: JobsDep, max_gaussians: MaxGaussians = None) -> StreamingResponse:
    """The 3DGS PLY layout (binary little-endian float32), with feat_* / label_* extra properties."""
    return await _export(session, jobs, max_gaussians, ply_file, ".ply", features=True)


@router.get("/{session_id}/gaussians.splat", response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}}})
async def export_splat(session: SessionDep, jobs: JobsDep, max_gaussians: MaxGaussians = None) -> StreamingResponse:
    """antimatter15 .splat: 32 bytes per Gaussian, most important first."""
    return await _export(session, jobs, max_gaussians, splat_file, ".splat", features=False)  # colour only


@router.get("/{session_id}/mesh.ply", response_class=Response,
            responses={200: {"content": {"application/octet-stream": {}}}, 409: {"model": ErrorBody}})
async def export_mesh(session: SessionDep, jobs: JobsDep, min_support: MinSupport = 0.0) -> Response:
    """The surface as a coloured triangle mesh: binary little-endian PLY, vertices (float x, y, z;
    uchar red, green, blue), faces (uchar count, int vertex_indices), counter-clockwise seen from the
    cameras' side. Marching cubes of the signed distance to the voxels' tangent planes
    (`canonical_core.scene.mesh`). 409 while the session holds no surface (no frames, or none above
    ``min_support``)."""
    def job():
        mesh = session.mesh(min_support)
        return mesh, mesh_ply_bytes(mesh) if len(mesh) else b""

    mesh, data = await jobs.run(job, kind="work", session=session.id)
    if not len(mesh):
        frames = session.scene.frames
        if frames and min_support > 0:  # the frames made voxels; none has the support asked for
            raise ApiError(409, "no_surface", f"min_support: no voxel of session {session.id} reaches {min_support:g} "
                           f"({frames} frames folded); ask for less", "min_support")
        raise ApiError(409, "no_surface", f"frames: session {session.id} holds no surface to mesh yet "
                       f"({frames} frames folded, min_support {min_support:g}); send frames first", "frames")
    return Response(data, media_type="application/octet-stream", headers={
        "Content-Disposition": f'attachment; filename="{session.id}.mesh.ply"',
        "X-Canonical-Vertices": str(len(mesh.vertices)), "X-Canonical-Faces": str(len(mesh))})
