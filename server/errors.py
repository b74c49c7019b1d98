"""One error shape for every failure: ``{"error": {"code", "message", "field"}}``.

Library errors are ValueErrors whose message starts with the offending field and ": "; they become
422 (409 for CapacityError). Bad input never reaches a 500.
"""

from __future__ import annotations

import json
import logging
import re

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from canonical_core.config.migration import FLAT_NAMES
from canonical_core.scene import CapacityError
from canonical_core.scene.corrections import FieldError

from .framelog import StorageError
from .scheduler import ClientGone, QueueFull
from .session_errors import (FrameIdConflict, FrameOutOfOrder, FramesAhead, MemoryBudgetBusy, MemoryBudgetExceeded, SessionNotFound,
                             SessionUnavailable, TooManySessions)
from .wire import WireError

log = logging.getLogger("canonical.server")

_FIELD = re.compile(r"^([A-Za-z_][\w.\[\]-]*): ")
QUEUE_RETRY_AFTER_S = 1  # a full queue: its jobs take a fraction of a second each
_HTTP_CODES = {401: "unauthorized", 404: "not_found", 405: "method_not_allowed",
               406: "not_acceptable", 409: "conflict", 413: "too_large", 415: "unsupported_media_type",
               422: "invalid_value", 429: "busy", 503: "unavailable", 507: "insufficient_storage"}


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str, field: str | None = None, headers: dict | None = None):
        super().__init__(message)
        self.status, self.code, self.message, self.field, self.headers = status, code, message, field, headers


class _AsciiJSON(JSONResponse):
    """JSON with every non-ASCII character escaped: an error names what the client sent, and a key
    that is not valid text (a lone surrogate, which JSON can carry) has no UTF-8 to be written in."""

    def render(self, content) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


def error_response(status: int, code: str, message: str, field: str | None = None, headers: dict | None = None) -> JSONResponse:
    return _AsciiJSON({"error": {"code": code, "message": message, "field": field}}, status_code=status, headers=headers)


def field_of(message: str) -> str | None:
    """The field a library message names (``"c2w: rotation is not orthonormal"`` -> ``"c2w"``)."""
    match = _FIELD.match(message)
    return match.group(1) if match else None


def from_value_error(exc: ValueError) -> ApiError:
    message = str(exc)
    if isinstance(exc, WireError):
        return ApiError(exc.status, exc.code, message, exc.field)
    if isinstance(exc, CapacityError):
        return ApiError(409, "capacity", message, field_of(message) or "max_voxels")
    if isinstance(exc, FrameIdConflict):
        return ApiError(409, "frame_id_conflict", message, "frame_id")
    if isinstance(exc, FrameOutOfOrder):
        return ApiError(409, "frame_out_of_order", message, exc.field)
    return ApiError(422, "invalid_value", message, exc.field if isinstance(exc, FieldError) else field_of(message))


def unparsable(exc: BaseException) -> str:
    """Why a JSON text could not be decoded, in words (Python's JSON decoder recurses per nesting level:
    a deep enough text ends in a RecursionError, which is the text's fault, not the service's)."""
    if isinstance(exc, RecursionError):
        return "nested too deeply"
    if isinstance(exc, UnicodeError):
        return "not UTF-8 text"
    return str(exc) or type(exc).__name__


def _validation_field(loc) -> str:
    parts = [str(p) for p in loc if p not in ("body", "query", "path", "header")]
    return ".".join(parts) if parts else "body"


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api(request: Request, exc: ApiError):
        return error_response(exc.status, exc.code, exc.message, exc.field, exc.headers)

    @app.exception_handler(ValueError)
    async def _value(request: Request, exc: ValueError):
        err = from_value_error(exc)
        return error_response(err.status, err.code, err.message, err.field)

    @app.exception_handler(SessionNotFound)
    async def _not_found(request: Request, exc: SessionNotFound):
        return error_response(404, "not_found", "session_id: no such session", "session_id")

    @app.exception_handler(SessionUnavailable)
    async def _unavailable(request: Request, exc: SessionUnavailable):
        status = 503 if exc.retry_later else 409
        return error_response(status, "session_unavailable", f"session_id: {exc.reason}", "session_id")

    @app.exception_handler(StorageError)
    async def _storage(request: Request, exc: StorageError):
        # nothing of the request was applied: the frame was not logged, so it was not folded either
        request.app.state.metrics.storage_errors += 1
        # the operator's to fix (a full or failing disk): said where they look, not only to the client
        log.error("%s %s: %s; the request was not applied", request.method, request.url.path, exc.strerror)
        status, code = (507, "insufficient_storage") if exc.full else (503, "storage_unavailable")
        return error_response(status, code, f"data_dir: {exc.strerror}; the request was not applied", "data_dir",
                              {"Retry-After": "30"})

    @app.exception_handler(FramesAhead)
    async def _ahead(request: Request, exc: FramesAhead):
        return error_response(429, "busy", str(exc), exc.field, {"Retry-After": "1"})

    @app.exception_handler(MemoryBudgetExceeded)
    async def _over_budget(request: Request, exc: MemoryBudgetExceeded):
        return error_response(413, "too_large", str(exc), "frame")

    @app.exception_handler(MemoryBudgetBusy)
    async def _budget_busy(request: Request, exc: MemoryBudgetBusy):
        return error_response(429, "busy", str(exc), "frame", {"Retry-After": "1"})

    @app.exception_handler(ClientGone)
    async def _client_gone(request: Request, exc: ClientGone):
        # nginx's code for it: nobody reads this answer, but a log line or a proxy may
        return error_response(499, "client_closed_request", "the client closed the connection before the answer",
                              "request")

    @app.exception_handler(QueueFull)
    async def _queue_full(request: Request, exc: QueueFull):
        return error_response(429, "busy", str(exc), "queue_limit", {"Retry-After": str(QUEUE_RETRY_AFTER_S)})

    @app.exception_handler(TooManySessions)
    async def _too_many(request: Request, exc: TooManySessions):
        return error_response(409, "too_many_sessions", str(exc), "max_sessions")

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = exc.errors()
        first = errors[0] if errors else {"loc": (), "msg": "invalid request", "type": ""}
        field = _validation_field(first.get("loc", ()))
        msg = first.get("msg", "invalid value")
        if first.get("type") == "extra_forbidden":
            # a session's settings under their old flat name (as sessions stored them once): where it is now
            moved = FLAT_NAMES.get(field) if request.url.path.rstrip("/") == "/v1/sessions" else None
            msg = "unknown field" + (f" (it is {moved} now)" if moved else "")
        elif first.get("type") == "missing":
            msg = "required field is missing"
        elif first.get("type") == "value_error" and field_of(own := msg.removeprefix("Value error, ")):
            # a settings group's own check names the full path of its field (``range.near: ...``)
            return error_response(422, "invalid_value", own, field_of(own))
        status, code = 422, "invalid_value"
        media = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if (tuple(first.get("loc", ())) == ("body",) and first.get("type") != "missing"
                and not (media == "application/json" or media.endswith("+json"))):
            # FastAPI decodes a body as JSON only when it says it is; any other is bytes, "not an object"
            return error_response(415, "unsupported_media_type", f"Content-Type: expected application/json, got "
                                  f"{media or 'none'}", "Content-Type")
        if first.get("type") == "json_invalid":
            status, code, field = 400, "malformed_body", "body"
            msg = f"not valid JSON ({first.get('ctx', {}).get('error', msg)})"
        return error_response(status, code, f"{field}: {msg}", field)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 400:  # FastAPI's answer to a body it failed to decode, a JSONDecodeError aside (above)
            cause = exc.__cause__
            problem = exc.detail if cause is None else f"not valid JSON ({unparsable(cause)})"
            return error_response(400, "malformed_body", f"body: {problem}", "body")
        field = {404: "path", 405: "method"}.get(exc.status_code)
        message = f"{request.method} {request.url.path}: {exc.detail}"
        return error_response(exc.status_code, _HTTP_CODES.get(exc.status_code, "error"), message, field, exc.headers)

    @app.exception_handler(Exception)
    async def _internal(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal", f"internal error ({type(exc).__name__}); the request was not applied")
