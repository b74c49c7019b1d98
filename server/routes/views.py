"""Views of a session at a camera: rendered image, feature splat, label map (POST JSON or GET query)."""

from __future__ import annotations

import math
import time
from typing import Annotated, Callable, NamedTuple

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response

from canonical_core import Camera
from canonical_core.calibration import validate_pose
from canonical_core.rendering import Colour, DepthMode, render
from canonical_core.rendering.preview import feature_preview

from .. import wire
from ..deps import JobsDep, MetricsDep, SessionDep, SettingsDep
from ..errors import ApiError
from ..memory import trim_heap
from ..scheduler import Kind as JobKind
from ..schemas import ErrorBody, ViewRequest
from ..solves import solve_soon

router = APIRouter(prefix="/v1/sessions", tags=["views"])

MSGPACK = "application/msgpack"
PNG = "image/png"
_ERRORS = {c: {"model": ErrorBody} for c in (401, 404, 409, 413, 422, 429)}


def _responses(*media: str) -> dict:
    return {200: {"content": {m: {} for m in media}}, **_ERRORS}


def wants_msgpack(request: Request) -> bool:
    """The first of PNG / msgpack that Accept lists; PNG when it lists neither (browsers, */*)."""
    for item in request.headers.get("accept", "").split(","):
        kind = item.split(";")[0].strip().lower()
        if kind in (MSGPACK, "application/x-msgpack", "application/vnd.msgpack"):
            return True
        if kind == PNG:
            return False
    return False


def _numbers(text: str, field: str, count: int, lo: float = -math.inf, hi: float = math.inf) -> list[float]:
    """``count`` comma-separated finite numbers in [lo, hi] from a query value; a 422 naming ``field``
    otherwise (NaN, infinities and numbers that overflow a float are never a camera or a colour)."""
    try:
        values = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        raise ApiError(422, "invalid_value", f"{field}: expected {count} comma-separated numbers, got {text[:200]!r}", field) from None
    if len(values) != count:
        raise ApiError(422, "invalid_value", f"{field}: expected {count} comma-separated numbers, got {len(values)}", field)
    if not all(math.isfinite(v) and lo <= v <= hi for v in values):
        bounds = "finite numbers" if (lo, hi) == (-math.inf, math.inf) else f"numbers in [{lo:g}, {hi:g}]"
        raise ApiError(422, "invalid_value", f"{field}: expected {bounds}, got {text[:200]!r}", field)
    return values


async def view_from_query(
    pose: Annotated[str, Query(description="c2w as 16 comma-separated numbers, row-major (OpenCV axes)")],
    K: Annotated[str, Query(description="fx,fy,cx,cy in pixels")],
    width: Annotated[int, Query(gt=0)],
    height: Annotated[int, Query(gt=0)],
    max_gaussians: Annotated[int | None, Query(ge=0)] = None,
    background: Annotated[str | None, Query(description="r,g,b in [0, 1]")] = None,
    colour: Annotated[Colour, Query(description="render only: normalised (default) or composited")] = "normalised",
    depth: Annotated[DepthMode, Query(description="render only, msgpack: median (default) or expected depth")] = "median",
) -> ViewRequest:
    p = _numbers(pose, "pose", 16)
    fx, fy, cx, cy = _numbers(K, "K", 4)
    c2w = [p[0:4], p[4:8], p[8:12], p[12:16]]
    validate_pose(c2w, "pose")  # the camera's own check, named as this request names the matrix
    return ViewRequest(K=[[fx, 0, cx], [0, fy, cy], [0, 0, 1]], c2w=c2w,
                       width=width, height=height, max_gaussians=max_gaussians,
                       background=None if background is None else _numbers(background, "background", 3, 0.0, 1.0), colour=colour,
                       depth=depth)


QueryView = Annotated[ViewRequest, Depends(view_from_query)]


def _camera(view: ViewRequest, max_pixels: int) -> Camera:
    wire.check_pixels(view.width, view.height, "width", max_pixels)
    return Camera(view.K, view.c2w, view.width, view.height)  # ValueError naming K / c2w -> 422


def view_channels(kind: str, feature_dim: int, label_dim: int) -> int:
    """float32 channels a view renders per pixel (what its memory and its response grow with)."""
    return {"render": 5, "features": feature_dim + 1, "segmentation": label_dim + 1}[kind]


def check_view_bytes(view: ViewRequest, channels: int, max_bytes: int) -> None:
    """413 naming ``width`` when the view's float maps (pixels x channels x 4 bytes) exceed ``max_bytes``."""
    size = view.width * view.height * channels * 4
    if size > max_bytes:
        raise ApiError(413, "too_large", f"width: a {view.width}x{view.height} view of {channels} channels needs {size} bytes, "
                                         f"above the limit of {max_bytes} (max_response_bytes); ask for a smaller view", "width")


# a view this large (4 MP) gives its work arrays' memory back once answered: glibc would keep it, and
# a few large views a minute would hold gigabytes
LARGE_VIEW_PIXELS = 1 << 22
# every map a view of each kind can give (a response may need fewer: `Encoder.outputs`)
OUTPUTS = {"render": ("rgb", "depth", "alpha"), "features": ("features", "alpha"), "segmentation": ("labels", "alpha")}


class Encoder(NamedTuple):
    """The maps a response needs, and how they become its body: maps -> (bytes, media type)."""

    outputs: tuple[str, ...]
    encode: Callable[[dict[str, np.ndarray]], tuple[bytes, str]]


async def _view(kind: str, session, view: ViewRequest, settings, jobs, metrics, encoder: Encoder,
                lane: JobKind = "work", coalesce: str | None = None) -> Response:
    """Render ``kind`` at the view on a worker of the scheduler's ``lane`` (`Scheduler.run`)."""
    camera = _camera(view, settings.max_image_pixels)
    outputs, encode = encoder
    if kind == "segmentation" and session.scene.label_dim == 0:
        raise _no_labels()
    check_view_bytes(view, view_channels(kind, session.scene.config.features.dim, session.scene.label_dim),
                     settings.max_response_bytes)

    def job():
        gaussians, label_dim = session.gaussians(view.max_gaussians, features=kind == "features")
        if kind == "segmentation" and label_dim == 0:
            raise _no_labels()
        result = render(gaussians, camera, outputs, background=view.background, colour=view.colour, depth_mode=view.depth,
                        num_threads=settings.threads)
        maps = {name: getattr(result, name).numpy() for name in outputs}
        encoded = encode(maps)
        del result, maps
        if camera.width * camera.height >= LARGE_VIEW_PIXELS:  # its work arrays' heap back to the system
            trim_heap()
        return encoded, len(gaussians)

    t0 = time.perf_counter()
    (content, media), n = await jobs.run(job, kind=lane, session=session.id, coalesce=coalesce)
    solve_soon(jobs.scheduler, session)  # a session restored with colours to solve gets them solved
    metrics.view_seconds[kind].observe(time.perf_counter() - t0)
    return Response(content, media_type=media, headers={"X-Canonical-Gaussians": str(n)})


def _no_labels() -> ApiError:
    return ApiError(409, "no_labels", "labels: this session has no fused labels; send frames with 'labels' to segment", "labels")


def _render_encoder(request: Request) -> Encoder:
    if wants_msgpack(request):
        return Encoder(OUTPUTS["render"], lambda m: (wire.pack({
            "rgb": wire.encode_array(wire.to_uint8(m["rgb"])), "depth": wire.encode_array(m["depth"].astype(np.float32)),
            "alpha": wire.encode_array(m["alpha"].astype(np.float32))}), MSGPACK))
    # a picture needs no depth (nor its median's test in the compositor)
    return Encoder(("rgb",), lambda m: (wire.encode_png(wire.to_uint8(m["rgb"])), PNG))


def _features_encoder(preview: str | None) -> Encoder:
    if preview is not None:
        if preview != "png":
            raise ApiError(422, "invalid_value", f"preview: expected 'png', got {preview!r}", "preview")
        return Encoder(OUTPUTS["features"], lambda m: (wire.encode_png(feature_preview(m["features"], m["alpha"])), PNG))
    return Encoder(OUTPUTS["features"], lambda m: (wire.pack({
        "features": wire.encode_array(m["features"].astype(np.float16)),
        "alpha": wire.encode_array(m["alpha"].astype(np.float32))}), MSGPACK))


def _segmentation_encoder(request: Request) -> Encoder:
    if wants_msgpack(request):
        return Encoder(OUTPUTS["segmentation"], lambda m: (wire.pack({
            "labels": wire.encode_array(wire.labels_to_uint16(m["labels"])),
            "alpha": wire.encode_array(m["alpha"].astype(np.float32))}), MSGPACK))
    return Encoder(("labels",), lambda m: (wire.encode_label_png(m["labels"]), PNG))


@router.post("/{session_id}/render", response_class=Response, responses=_responses(PNG, MSGPACK))
async def render_post(view: ViewRequest, request: Request, session: SessionDep, settings: SettingsDep,
                      jobs: JobsDep, metrics: MetricsDep) -> Response:
    """Render at a camera. ``Accept: image/png`` (default) -> PNG; ``application/msgpack`` -> rgb uint8
    [H,W,3], depth float32 [H,W] (0 where nothing is drawn), alpha float32 [H,W]."""
    return await _view("render", session, view, settings, jobs, metrics, _render_encoder(request))


@router.get("/{session_id}/render", response_class=Response, responses=_responses(PNG, MSGPACK))
async def render_get(view: QueryView, request: Request, session: SessionDep, settings: SettingsDep,
                     jobs: JobsDep, metrics: MetricsDep) -> Response:
    """Render from query parameters (for browsers): ``?pose=16 numbers&K=fx,fy,cx,cy&width=&height=``."""
    return await _view("render", session, view, settings, jobs, metrics, _render_encoder(request))


@router.post("/{session_id}/features", response_class=Response, responses=_responses(MSGPACK, PNG))
async def features_post(view: ViewRequest, session: SessionDep, settings: SettingsDep, jobs: JobsDep,
                        metrics: MetricsDep, preview: str | None = None) -> Response:
    """Feature splat: msgpack ``features`` float16 [H,W,C] (composited, not normalised) and ``alpha``
    float32 [H,W]; with ``?preview=png`` a PCA-to-RGB picture."""
    return await _view("features", session, view, settings, jobs, metrics, _features_encoder(preview))


@router.get("/{session_id}/features", response_class=Response, responses=_responses(MSGPACK, PNG))
async def features_get(view: QueryView, session: SessionDep, settings: SettingsDep, jobs: JobsDep,
                       metrics: MetricsDep, preview: str | None = None) -> Response:
    return await _view("features", session, view, settings, jobs, metrics, _features_encoder(preview))


@router.post("/{session_id}/segmentation", response_class=Response, responses=_responses(PNG, MSGPACK))
async def segmentation_post(view: ViewRequest, request: Request, session: SessionDep, settings: SettingsDep,
                            jobs: JobsDep, metrics: MetricsDep) -> Response:
    """Label map from fused labels: a palette PNG (index 0 = nothing drawn, k + 1 = label k; fixed
    palette) or msgpack ``labels`` uint16 [H,W] (65535 = nothing drawn) + ``alpha``. 409 without labels."""
    return await _view("segmentation", session, view, settings, jobs, metrics, _segmentation_encoder(request))


@router.get("/{session_id}/segmentation", response_class=Response, responses=_responses(PNG, MSGPACK))
async def segmentation_get(view: QueryView, request: Request, session: SessionDep, settings: SettingsDep,
                           jobs: JobsDep, metrics: MetricsDep) -> Response:
    return await _view("segmentation", session, view, settings, jobs, metrics, _segmentation_encoder(request))
