"""What the SDK raises: `CanonicalError` (the service's 4xx/5xx answer), `ServiceUnreachable` (no
answer: the service could not be reached, or the connection broke), and for a stream of frames
`StreamStopped` (a frame the client could not send) and `StreamRefused` (a frame the service
refused), each with how far the stream got."""

from __future__ import annotations


class CanonicalError(Exception):
    """A 4xx/5xx answer: ``status``, ``code``, ``message`` and the offending ``field`` (or None)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None):
        Exception.__init__(self, f"{status} {code}: {message}")  # not the next class's in a subclass's order
        self.status, self.code, self.message, self.field = status, code, message, field


class ServiceUnreachable(ConnectionError):
    """No answer from the service: it could not be reached, the connection broke or the request timed
    out (after the retries the request allows); the transport's error is the cause."""


class StreamStopped(Exception):
    """A stream of `Session.add_frames` stopped at a frame: its ``index`` in the session's stream, and
    how many frames of the call were ``acknowledged`` before it (folded, their reports yielded). Raised
    as it is where the client could not send the frame (the error is its ``__cause__``); a refusal by
    the service is the `StreamRefused` subclass."""

    def __init__(self, error: BaseException, index: int, acknowledged: int):
        super().__init__(f"the stream stopped at frame {index} ({acknowledged} acknowledged before it; where the "
                         f"connection broke after it was sent, it may have been folded): {type(error).__name__}: {error}")
        self.index, self.acknowledged = index, acknowledged


class StreamRefused(CanonicalError, StreamStopped):
    """A frame of `Session.add_frames` was refused: its ``index`` in the session's stream, and how many
    frames of the call were ``acknowledged`` before it (folded, their reports yielded); the refusal's
    status, code, message and field as `CanonicalError`'s."""

    def __init__(self, refusal: CanonicalError, index: int, acknowledged: int):
        message = f"frame {index} refused (the session holds the {index} frames before it): {refusal.message}"
        CanonicalError.__init__(self, refusal.status, refusal.code, message, refusal.field)
        self.index, self.acknowledged = index, acknowledged
