"""The web viewer: its pages, the images it draws, its live fold events and the input cameras.

Pages (``/``, ``/sessions/{id}/view``, ``/viewer/<file>``) are static and carry no session data, so
they are served without the token; the page asks for the token and sends it as a bearer header on
every data request below (never in the URL).
"""

from __future__ import annotations

import asyncio
import io
import json
import math
import mimetypes
import time
from contextlib import aclosing
from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response, StreamingResponse
from PIL import Image

from canonical_core.config import MAX_DEPTH
from canonical_core.rendering.preview import feature_preview

from .. import viewer, wire
from ..deps import JobsDep, MetricsDep, SessionDep, SettingsDep, StoreDep
from ..errors import ApiError
from ..events import DROPPED, FoldBatch, Published, TooManyStreams, sse
from ..scheduler import Superseded
from ..schemas import ErrorBody, InputCamerasOut, ViewerInfo, ViewerSessionList
from ..session_errors import SessionNotFound
from . import views

pages = APIRouter(include_in_schema=False)
router = APIRouter(prefix="/v1/sessions", tags=["viewer"])
info_router = APIRouter(prefix="/v1/viewer", tags=["viewer"])

Mode = Literal["rgb", "depth", "alpha", "features", "labels"]
ImageFormat = Literal["png", "jpeg", "webp"]
MEDIA = {"png": "image/png", "jpeg": "image/jpeg", "webp": "image/webp"}
MAX_SIDE = {"jpeg": 65500, "webp": 16383}  # pixels a side the format can hold (PNG: more than a view may have)
KEEPALIVE_S = 15.0  # an SSE comment this often keeps proxies from closing an idle stream
DELETED_CHECK_S = 1.0  # an open stream looks this often whether its session was deleted (it then ends)
STREAM_RETRY_AFTER_S = 5  # a stream refused over a cap: streams end when viewers leave, not at once
PAGE_HEADERS = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}
MIN_DEPTH_SPAN = 1e-6  # metres: the narrowest depth_range a depth picture is coloured over


# -- pages -----------------------------------------------------------------------------------------
def _static(name: str) -> Response:
    path = viewer.STATIC / name
    if "/" in name or name.startswith(".") or not path.is_file():
        raise ApiError(404, "not_found", f"path: no viewer file {name!r}", "path")
    media = mimetypes.guess_type(name)[0] or "application/octet-stream"
    if name.endswith(".js"):
        media = "text/javascript"  # ES modules need a JavaScript type whatever the host's mime table says
    return Response(path.read_bytes(), media_type=media, headers=PAGE_HEADERS)


@pages.get("/")
async def index_page() -> Response:
    """The session list."""
    return _static("index.html")


@pages.get("/sessions/{session_id}/view")
async def view_page(session_id: str) -> Response:
    """The viewer of one session (the page reads the id from its URL)."""
    return _static("view.html")


@pages.get("/viewer/{name}")
async def viewer_file(name: str) -> Response:
    return _static(name)


def is_page(path: str) -> bool:
    """Whether ``path`` is a viewer page or asset (static, no session data: open without the token)."""
    parts = path.split("/")
    return (path == "/" or path.startswith("/viewer/")
            or (len(parts) == 4 and parts[1] == "sessions" and parts[3] == "view"))


# -- data for the pages ----------------------------------------------------------------------------
@info_router.get("/info", response_model=ViewerInfo, responses={401: {"model": ErrorBody}})
async def viewer_info(settings: SettingsDep) -> ViewerInfo:
    """The depth colour map (near first) and the label palette (index k + 1 = label k), so the page
    draws the scale bar and the legend in the server's colours; the largest picture it renders, so
    the page fits its size to it."""
    most = min(settings.max_image_pixels, settings.max_response_bytes // (4 * views.view_channels("render", 0, 0)))
    return ViewerInfo(depth_colormap=viewer.DEPTH_LUT.tolist(), label_palette=viewer.PALETTE.tolist(),
                      max_picture_pixels=most)


@info_router.get("/sessions", response_model=ViewerSessionList, responses={401: {"model": ErrorBody}})
async def viewer_sessions(request: Request, store: StoreDep, jobs: JobsDep) -> ViewerSessionList:
    """Every session with its stats and the time of its last fold (null when unknown)."""
    events = request.app.state.events

    def job():
        rows = []
        for session in store.list():
            try:
                rows.append({**session.stats(), "last_fold": events.last_fold_time(session)})
            except SessionNotFound:  # deleted since the list was taken
                continue
        return rows

    rows = await jobs.run(job, kind="viewer")
    rows += [{**s, "last_fold": None} for s in store.unavailable_summaries()]
    return ViewerSessionList(sessions=rows)


@router.get("/{session_id}/cameras", response_model=InputCamerasOut,
            responses={c: {"model": ErrorBody} for c in (401, 404, 422)})
async def input_cameras(
    request: Request,
    session: SessionDep,
    since: Annotated[int | None, Query(ge=0, description=(
        "only the cameras of frames from this frame_index on (a client that follows a stream reads "
        "what is new); absent: every camera"))] = None,
) -> Response:
    """The input cameras, oldest first: ``frame_index``, ``width``, ``height``, ``K`` (fx, fy, cx, cy),
    ``c2w`` (16 numbers, row-major, OpenCV axes): the poses the viewer snaps to and draws. With the
    last fold's unix time and its age in seconds on the service's clock, so that a page tells a
    running stream from its own clock's skew. The body is written from the track's rows directly:
    validating a long track's thousands of cameras as models cost more than reading them."""
    events = request.app.state.events
    cameras = await run_in_threadpool(events.track, session, since or 0)
    last = events.last_fold_time(session)
    head = {"id": session.id, "frames": session.counts()[0], "label_dim": session.scene.label_dim, "last_fold": last,
            "last_fold_age": None if last is None else max(0.0, time.time() - last), "cameras": cameras}
    return Response(json.dumps(head, separators=(",", ":")), media_type="application/json")


async def _next_event(queue: asyncio.Queue, closing: asyncio.Event, timeout: float) -> Published | None:
    """The next event of ``queue``; None after ``timeout`` seconds or once ``closing`` is set."""
    getter, stop = asyncio.ensure_future(queue.get()), asyncio.ensure_future(closing.wait())
    try:
        done, _ = await asyncio.wait({getter, stop}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED)
        return getter.result() if getter in done else None
    finally:  # also when the stream is closed while waiting: no task is left pending
        getter.cancel()
        stop.cancel()


@router.get("/{session_id}/events", responses={200: {"content": {"text/event-stream": {}}},
                                               **{c: {"model": ErrorBody} for c in (401, 404, 422, 429)}})
async def fold_events(
    request: Request,
    session: SessionDep,
    every: Annotated[float | None, Query(gt=0, le=60, description=(
        "seconds: at most one fold event per this interval, standing for the folds since the last "
        "(their count, cameras and latest warnings); absent: one event per fold"))] = None,
) -> StreamingResponse:
    """Server-Sent Events: ``state`` at once (frames, voxels, label_dim), then ``fold`` after each
    acknowledged fold (frames, voxels, the fold report, the frame's camera), or with ``every`` at most
    one per interval (`events.FoldBatch`: the first fold after a quiet interval at once, the rest when
    the interval is up); ``corrected`` (as ``state``) once a pose correction or a frame removal has
    changed the scene, and ``recoloured`` (as ``state``) once a colour solve in the background has
    changed its colours (a page redraws), each within `DELETED_CHECK_S`; a comment every 15 s when idle; the stream ends when the session is deleted
    (with a ``deleted`` event, within `DELETED_CHECK_S`), the service stops, or the client falls
    behind by more than the stream's queue (a last ``dropped`` event; reconnect for the latest
    state). Open streams are capped per session and per service: 429 over a cap, naming its setting."""
    events = request.app.state.events
    try:
        queue = events.subscribe(session.id)
    except TooManyStreams as exc:
        raise ApiError(429, "busy", str(exc), exc.setting, {"Retry-After": str(STREAM_RETRY_AFTER_S)}) from None

    loop = asyncio.get_running_loop()
    last_sent = loop.time()  # when the stream last sent anything, keep-alives included

    seen = (session.corrected, session.recoloured)

    def changed() -> bytes | None:
        """A ``corrected`` event once a correction changed the served scene since the stream last
        looked (the page then reads the track again and redraws), else ``recoloured`` once a colour
        solve did (the page redraws), else None (a solve seen at the same look as a correction needs
        no event of its own: the page redraws for the correction)."""
        nonlocal seen
        before, seen = seen, (session.corrected, session.recoloured)
        if before[0] != seen[0]:
            return sse("corrected", state())
        return sse("recoloured", state()) if before[1] != seen[1] else None

    def state() -> dict:
        frames, voxels = session.counts()
        return {"frames": frames, "voxels": voxels, "label_dim": session.scene.label_dim}

    def after_wait() -> tuple[bytes | None, bool]:
        """What a stream sends after a wait with no fold to send, and whether it ends there: the end
        if the session was deleted (by any route or the retention policy), a keep-alive once it has
        been quiet for KEEPALIVE_S."""
        if session.deleted:
            return sse("deleted", {"id": session.id}), True
        if events.closing.is_set() or loop.time() - last_sent < KEEPALIVE_S:
            return None, False
        return b": keep-alive\n\n", False

    async def each_fold():
        while not events.closing.is_set():
            item = await _next_event(queue, events.closing, DELETED_CHECK_S)
            if (news := changed()) is not None:
                yield news
            if item is not None:
                yield item.data
                if item is DROPPED:
                    return
                continue
            data, end = after_wait()
            if data is not None:
                yield data
            if end:
                return

    async def batched(interval: float):
        batch, batch_sent_at = FoldBatch(), -math.inf
        while not events.closing.is_set():
            wait = batch_sent_at + interval - loop.time() if batch.pending else DELETED_CHECK_S
            item = await _next_event(queue, events.closing, min(wait, DELETED_CHECK_S)) if wait > 0 else None
            if item is DROPPED:
                yield item.data
                return
            if item is not None:
                batch.add(item.event)
            if (news := changed()) is not None:  # after the folds before it
                if batch.pending:
                    yield sse("fold", batch.take())
                    batch_sent_at = loop.time()
                yield news
            if batch.pending and loop.time() >= batch_sent_at + interval:  # a fold after a quiet interval, or the interval is up
                yield sse("fold", batch.take())
                batch_sent_at = loop.time()
                continue
            if item is None:
                data, end = after_wait()
                if data is not None:
                    yield data
                if end:
                    return

    async def stream():
        nonlocal last_sent
        try:
            yield sse("state", state())
            async with aclosing(each_fold() if every is None else batched(every)) as sent:  # closed with the stream
                async for data in sent:
                    yield data
                    last_sent = loop.time()
        finally:
            events.unsubscribe(session.id, queue)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


# -- images ----------------------------------------------------------------------------------------
def encode_image(rgb, fmt: ImageFormat, quality: int) -> bytes:
    """uint8 [H, W, 3] -> PNG (lossless, the render route's encoder), JPEG or WebP at ``quality``."""
    if fmt == "png":
        return wire.encode_png(rgb)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt.upper(), quality=quality)
    return buf.getvalue()


def check_format_size(view, fmt: ImageFormat) -> None:
    """422 naming ``width`` or ``height`` where the picture would be larger than ``fmt`` can hold:
    checked before rendering, as the encoder would refuse it only after."""
    limit = MAX_SIDE.get(fmt)
    for field, size in (("width", view.width), ("height", view.height)):
        if limit is not None and size > limit:
            raise ApiError(422, "invalid_value", f"{field}: a {fmt} picture is at most {limit} pixels a side, got "
                                                 f"{size}; ask for a smaller view or format=png", field)


def picture(mode: Mode, maps: dict, fixed_range: tuple[float, float] | None) -> tuple:
    """The maps of one view -> (uint8 [H, W, 3] picture, response headers saying how to read it)."""
    if "depth" in maps:  # the viewer orbits about the surface in the middle of the view
        centre = viewer.centre_depth(maps["depth"], maps["alpha"])
        headers = {} if centre is None else {"X-Canonical-Centre-Depth": f"{centre:.6g}"}
        return _render_picture(mode, maps, fixed_range, headers)
    if mode == "features":
        return feature_preview(maps["features"], maps["alpha"]), {}
    ids = viewer.visible_labels(maps["labels"])
    return viewer.label_picture(maps["labels"]), {"X-Canonical-Labels": ",".join(map(str, ids))}


def _render_picture(mode: Mode, maps: dict, fixed_range, headers: dict) -> tuple:
    if mode == "rgb":
        return wire.to_uint8(maps["rgb"]), headers
    if mode == "depth":
        near_far = fixed_range or viewer.depth_range(maps["depth"], maps["alpha"])
        return (viewer.depth_picture(maps["depth"], maps["alpha"], near_far),
                {**headers, "X-Canonical-Depth-Range": f"{near_far[0]:.6g},{near_far[1]:.6g}"})
    covered = float((maps["alpha"] > 0.5).mean())
    return viewer.coverage_picture(maps["alpha"]), {**headers, "X-Canonical-Coverage": f"{covered:.4f}"}


def _range(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    near, far = views._numbers(text, "depth_range", 2, 0.0, MAX_DEPTH)
    if not far - near >= MIN_DEPTH_SPAN:  # a narrower span has no float32 depth inside it to colour
        raise ApiError(422, "invalid_value", f"depth_range: far must exceed near by at least {MIN_DEPTH_SPAN:g} m, "
                                             f"got {near:g}, {far:g}", "depth_range")
    return near, far


@router.get("/{session_id}/image", response_class=Response,
            responses={200: {"content": {m: {} for m in MEDIA.values()}},
                       204: {"description": "superseded: a newer picture of the same viewer replaced this one "
                                            "while it waited (X-Canonical-Superseded: true)"},
                       **{c: {"model": ErrorBody} for c in (401, 404, 409, 413, 422, 429)}})
async def view_image(
    view: views.QueryView, session: SessionDep, settings: SettingsDep, jobs: JobsDep, metrics: MetricsDep,
    mode: Annotated[Mode, Query(description="rgb (with `colour`), depth (colour-mapped), alpha (coverage), "
                                            "features (PCA to RGB), labels (palette colours)")] = "rgb",
    format: Annotated[ImageFormat, Query(description="png (lossless), jpeg or webp (smaller, faster to send; at "
                                                    "most 65500 and 16383 pixels a side)")] = "png",
    quality: Annotated[int, Query(ge=1, le=100, description="jpeg/webp quality")] = 80,
    depth_range: Annotated[str | None, Query(description="depth mode: near,far in metres (default: "
                                                         "the 2nd-98th percentile of the view)")] = None,
    x_canonical_viewer: Annotated[str | None, Header(max_length=64, description=(
        "the viewer page asking (any id it picked): its picture still waiting is replaced by this one"))] = None,
) -> Response:
    """A picture of the view for people (the web viewer): one mode, one image format.

    Headers: ``Server-Timing`` (``render``: queue + rasterise, ``picture``: colour mapping,
    ``encode``), ``X-Canonical-Gaussians``, and per mode ``X-Canonical-Depth-Range`` (near,far of
    the colour map), ``X-Canonical-Coverage`` (share of pixels with alpha > 0.5) or
    ``X-Canonical-Labels`` (label ids in view); rgb, depth and alpha also carry
    ``X-Canonical-Centre-Depth`` (the median depth drawn in the middle ninth of the view, where
    anything is drawn there: the viewer orbits about it). Labels: 409 where the session has none.

    Pictures are the service's last priority (after frames, renders and exports), and they coalesce:
    a picture still waiting when a newer one of the same viewer (``X-Canonical-Viewer``; without it,
    of the same session) arrives is answered 204 with ``X-Canonical-Superseded: true``, so a viewer
    that moves faster than the service renders costs one waiting picture, not a queue of stale ones."""
    check_format_size(view, format)
    fixed = _range(depth_range)
    kind = {"features": "features", "labels": "segmentation"}.get(mode, "render")
    timing: dict = {}

    def encode(maps):
        t0 = time.perf_counter()
        rgb, headers = picture(mode, maps, fixed)
        t1 = time.perf_counter()
        data = encode_image(rgb, format, quality)
        timing.update(headers, picture=t1 - t0, encode=time.perf_counter() - t1)
        return data, MEDIA[format]

    t0 = time.perf_counter()
    try:
        response = await views._view(kind, session, view, settings, jobs, metrics, views.Encoder(views.OUTPUTS[kind], encode),
                                     lane="viewer", coalesce=x_canonical_viewer or "")
    except Superseded:
        return Response(status_code=204, headers={"X-Canonical-Superseded": "true", "Cache-Control": "no-store"})
    total = time.perf_counter() - t0
    picture_s, encode_s = timing.pop("picture"), timing.pop("encode")
    response.headers.update(timing)
    response.headers["Server-Timing"] = (f"render;dur={1000 * (total - picture_s - encode_s):.2f}, "
                                         f"picture;dur={1000 * picture_s:.2f}, encode;dur={1000 * encode_s:.2f}")
    response.headers["Cache-Control"] = "no-store"
    return response
