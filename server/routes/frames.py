"""Fold frames into a session: msgpack (the SDK's format) or multipart/form-data (curl users)."""

from __future__ import annotations

import json
import time
from contextlib import nullcontext
from typing import Annotated

from fastapi import APIRouter, Header, Request, Response

from .. import wire
from ..deps import JobsDep, MetricsDep, SessionDep, SettingsDep
from ..errors import ApiError, unparsable
from ..memory import DecodedHold
from ..multipart import parse_form_data
from ..schemas import ErrorBody, FoldReportOut
from ..scheduler import ClientGone
from ..session_errors import MemoryBudgetExceeded
from ..solves import solve_soon

router = APIRouter(prefix="/v1/sessions", tags=["frames"])

MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")
FRAME_TYPES = (*MSGPACK_TYPES, "multipart/form-data")  # the bodies `max_body_bytes` is for
CAMERA_FIELDS = ("K", "c2w", "depth_scale", "num_classes", "frame_id", "width", "height")
STOPPING_RETRY_AFTER_S = 5  # a first resend soon: while the service is down, the SDK backs off on its own
# digits only: int() would also read "1_0" as 10, "+1" and " 1" as 1
FrameIndex = Annotated[str | None, Header(alias="Frame-Index", pattern=r"^[0-9]{1,18}$", description=(
    "the frame's place in the session's stream (0 for its first frame): numbered frames fold in this order"))]


def media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def parse_multipart(content_type: str, body: bytes) -> dict:
    """multipart/form-data with parts ``rgb`` (or ``image``; PNG/JPEG), optional ``depth`` (16-bit PNG),
    optional ``labels`` (a class map PNG: 0 no class, k + 1 class k; with ``num_classes``) and
    ``camera`` (JSON: K, c2w, depth_scale, num_classes, frame_id, width, height) -> a frame message.
    Each part at most once; JSON values keep their types (a string is not a number)."""
    out: dict = {}
    seen: set[str] = set()
    for part in parse_form_data(content_type, body):
        name = "rgb" if part.name == "image" else part.name
        if name not in ("rgb", "depth", "labels", "camera"):
            raise wire.WireError(name, "unknown form part (expected rgb, depth, labels, camera)")
        if name in seen:
            raise wire.WireError(name, "form part given more than once")
        seen.add(name)
        if name != "camera":
            out[name] = part.data
            continue
        try:
            camera = json.loads(part.data, parse_constant=_no_constant)
        except (ValueError, RecursionError) as exc:
            raise wire.WireError("camera", f"not valid JSON ({unparsable(exc)})") from None
        if not isinstance(camera, dict):
            raise wire.WireError("camera", f"expected a JSON object with {list(CAMERA_FIELDS)}")
        unknown = sorted(k for k in camera if k not in CAMERA_FIELDS)
        if unknown:
            raise wire.WireError(unknown[0], f"unknown camera field (known: {list(CAMERA_FIELDS)})")
        out.update(camera)
    if "camera" not in seen:
        raise wire.WireError("camera", "required form part is missing (JSON with K and c2w)")
    return out


def _no_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def frame_limits(settings) -> wire.FrameLimits:
    return wire.FrameLimits(settings.max_image_pixels, settings.max_rgb_only_pixels, settings.max_label_channels,
                            settings.max_channel_values)


def check_session_accepts(frame, config) -> None:
    """Client features sent to a session that computes its own would be dropped unseen: 422."""
    if frame.features is not None and config.features.backend != "client":
        raise wire.WireError("features", f"this session computes its own features (features.backend="
                                         f"{config.features.backend!r}); send features only to a session created "
                                         f"with features.backend='client'")


def body_refused(scope, why: str) -> None:
    """A numbered frame whose body the service refused before its route ran (too large, too slow to
    arrive): the frames numbered after it stop waiting for it, as for a frame the route refuses
    (``app.state.frame_refused``: the app's `SessionStore.frame_refused`, or a cluster's owner told)."""
    headers = dict(scope["headers"])
    index, parts = headers.get(b"frame-index", b""), scope.get("path", "").split("/")
    if scope.get("method") != "POST" or not index.isdigit() or len(parts) != 5 or parts[:3] != ["", "v1", "sessions"] \
            or parts[4] != "frames":
        return
    scope["app"].state.frame_refused(parts[3], int(index), why)


def still_wanted(request: Request, session, index: int) -> None:
    """Raise where a frame waiting for its turn will not get it: its session was deleted (404), or the
    service is stopping (503: not folded, so a client sends it again once the service is back)."""
    session.check_alive()
    if request.app.state.events.closing.is_set():  # set on SIGTERM / SIGINT, before the graceful wait
        raise ApiError(503, "unavailable", f"Frame-Index: the service is stopping, and frame {index} still waited "
                                           f"for frame {session.scene.frames}: it was not folded; send it again once "
                                           "the service is back", "Frame-Index",
                       {"Retry-After": str(STOPPING_RETRY_AFTER_S)})


@router.post("/{session_id}/frames", response_model=FoldReportOut,
             responses={c: {"model": ErrorBody} for c in (400, 401, 404, 409, 413, 415, 422, 429, 503, 507)},
             openapi_extra={"requestBody": {"content": {"application/msgpack": {}, "multipart/form-data": {}}}})
async def add_frame(request: Request, response: Response, session: SessionDep, settings: SettingsDep, jobs: JobsDep,
                    metrics: MetricsDep, frame_index: FrameIndex = None) -> FoldReportOut:
    """Validate, log (fsync) and fold one posed frame; the report says what changed.

    Idempotent on ``frame_id``: a frame the session already folded (a retry after a lost answer) is
    not folded again; its first report comes back with ``Idempotent-Replay: true`` (409 if its
    content differs). A frame that cannot be made durable is not folded: 507 (disk full) or 503.

    Header ``Frame-Index`` (optional): the frame's place in the session's stream, for clients that
    keep several frames in flight. The frame is validated at once, then folded once the session
    holds the frames before it, in that order whatever order they arrive in; 409 when one of those
    was refused, when a correction removed frames while it was in flight, or when they do not come
    within ``frame_order_wait_s``; 404 once its session is deleted, 503 once the service stops; 429
    (sent again later, not a refusal) when `ordering.MAX_AHEAD` numbered frames of the session are
    already read ahead of their turn."""
    frame_index = None if frame_index is None else int(frame_index)
    kind = media_type(request)
    if kind not in FRAME_TYPES:
        exc = ApiError(415, "unsupported_media_type",
                       f"Content-Type: expected application/msgpack or multipart/form-data, got {kind or 'none'!r}",
                       "Content-Type")
        session.order.refused(frame_index, exc)
        raise exc
    body = await request.body()

    def parse():
        try:
            if kind == "multipart/form-data":
                msg, record = parse_multipart(request.headers["content-type"], body), None
            else:
                msg, record = wire.unpack(body), body
            frame = wire.frame_from_message(msg, limits=frame_limits(settings), fresh=True)  # validated before it is logged
            check_session_accepts(frame, session.scene.config)
            record = wire.pack(msg) if record is None else record  # a form's parts, logged as one message
            held = DecodedHold(session.budget, frame)
        except (ValueError, MemoryBudgetExceeded) as exc:
            session.order.refused(frame_index, exc)  # the frames numbered after it are not folded
            raise
        try:
            return record, frame, held, session.prepare(frame)  # its fold begun: evidence made while others fold
        except BaseException:
            held.release()
            raise

    async def left() -> None:  # a numbered frame whose client went while it waited: never answered, never folded
        if await request.is_disconnected():
            raise ClientGone(session.id)

    t0, ahead, held = time.perf_counter(), None, None
    try:
        # a numbered frame holds its arrays while it waits, outside any job queue: counted (`FrameOrder.ahead`)
        with session.order.ahead(frame_index, session.scene.frames) if frame_index is not None else nullcontext():
            record, frame, held, ahead = await jobs.run(parse, kind="ingest", session=session.id)  # while the frames before it fold
            decoded = time.perf_counter() - t0
            if frame_index is not None:  # on the loop, holding no job
                await session.order.wait_turn(frame_index, lambda: session.scene.frames, settings.frame_order_wait_s,
                                              lambda: still_wanted(request, session, frame_index), left)
        t0 = time.perf_counter()
        report, replay = await jobs.run(session.add_frame, record, frame, settings.snapshot_every_frames,
                                        settings.snapshot_every_seconds, frame_index, ahead and ahead.frame,
                                        kind="frame", session=session.id)
    finally:  # the colours of what the session holds now, solved while no frame of it waits
        if ahead is not None:
            ahead.release()
        if held is not None:
            held.release()
        solve_soon(jobs.scheduler, session)
    if replay:
        response.headers["Idempotent-Replay"] = "true"
    else:
        metrics.fold_seconds.observe(decoded + time.perf_counter() - t0)  # its turn's wait left out
        metrics.frames_total += 1
        request.app.state.events.folded(session, frame.camera, report)
    return FoldReportOut(**report.to_dict())
