"""What the sessions raise to their callers, in one module below every session module, so that the
routes and the CLI import the errors without the code that raises them. `server.errors` maps them to
HTTP answers."""

from __future__ import annotations


class SessionNotFound(KeyError):
    def __init__(self, session_id: str):
        super().__init__(session_id)
        self.session_id = session_id


class TooManySessions(RuntimeError):
    pass


class SessionUnavailable(RuntimeError):
    """A session whose files do not add up (or whose log cannot be written): not served, with the reason."""

    def __init__(self, session_id: str, reason: str, retry_later: bool = False):
        super().__init__(f"session {session_id}: {reason}")
        self.session_id, self.reason, self.retry_later = session_id, reason, retry_later


class MemoryBudgetExceeded(RuntimeError):
    """A frame whose fold could pass the service's memory budget (`server.memory`) beside what the
    sessions hold: 413."""


class MemoryBudgetBusy(RuntimeError):
    """A frame that fits the memory budget beside the sessions, but not beside the folds and decoded
    frames under way now, which give theirs back within moments: 429 with Retry-After."""


class FrameIdConflict(ValueError):
    """A frame_id that the session already folded, sent again with other content."""


class FrameOutOfOrder(ValueError):
    """A numbered frame (``Frame-Index``) that cannot be folded in its place: 409 naming ``field``."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class FramesAhead(Exception):
    """A numbered frame past the frames a session may hold read ahead of their turn: 429, sent again
    later (not a refusal: the frames numbered after it go on waiting for it)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class CorrectionRefused(ValueError):
    """A correction the session cannot take (no archive, or one that cannot serve it): 409 naming ``field``."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class DataDirLocked(RuntimeError):
    """Another process serves the data directory."""


class Unrestorable(RuntimeError):
    """The files of a session do not add up; the message says how, and what ``canonical repair`` can do."""


class SnapshotLost(Unrestorable):
    """A snapshot missing, unreadable or older than the log's first frame: the frames before the log's
    are not in the log (the frame archive may hold them)."""
