"""What the SDK raises for the service's refusals: `CanonicalError` (a 4xx/5xx answer) and
`StreamRefused` (a refused frame of a stream, with how far the stream got)."""

from __future__ import annotations


class CanonicalError(Exception):
    """A 4xx/5xx answer: ``status``, ``code``, ``message`` and the offending ``field`` (or None)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.field = status, code, message, field


class StreamRefused(CanonicalError):
    """A frame of `Session.add_frames` was refused: its ``index`` in the session's stream, and how many
    frames of the call were ``acknowledged`` before it (folded, their reports yielded); the refusal's
    status, code, message and field as `CanonicalError`'s."""

    def __init__(self, refusal: CanonicalError, index: int, acknowledged: int):
        message = f"frame {index} refused (the session holds the {index} frames before it): {refusal.message}"
        super().__init__(refusal.status, refusal.code, message, refusal.field)
        self.index, self.acknowledged = index, acknowledged
