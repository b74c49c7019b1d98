"""The order a session folds numbered frames in: their ``Frame-Index``, not their arrival.

A client that keeps several frames in flight (`client.sdk.Session.add_frames`) numbers them with their
place in the session's stream. Requests on different connections may reach the session in any order,
so a frame waits (on a condition of the session's lock) until the session holds exactly the frames
before it, and is folded then: the scene is the one that posting the frames one by one gives, run
after run. A frame whose turn does not come is refused instead of folded out of order: when a frame
before it was refused (the stream stops there), or when the gap is not filled within the wait.
Frames without an index fold in arrival order, as before.
"""

from __future__ import annotations

import threading
import time

from .session_errors import FrameOutOfOrder

FIELD = "Frame-Index"


class FrameOrder:
    """The turns of one session's numbered frames. Every method expects the caller to hold ``lock``
    (the session's), which `wait_turn` releases while it waits."""

    def __init__(self, lock: threading.Lock):
        self._turn = threading.Condition(lock)
        self._refused: dict[int, str] = {}  # index -> why the frame with that index was refused

    def wait_turn(self, index: int, frames, wait_s: float) -> None:
        """Return once ``frames()`` (the session's frame count) is ``index`` or more; raise
        `FrameOutOfOrder` when the frame at the gap was refused, or when no frame is folded for
        ``wait_s`` (a long pipeline that moves on keeps its frames waiting)."""
        deadline, last = time.monotonic() + wait_s, frames()
        while (held := frames()) < index:
            if held != last:
                deadline, last = time.monotonic() + wait_s, held
            if held in self._refused:
                raise FrameOutOfOrder(FIELD, f"frame {index} follows frame {held}, which was refused "
                                             f"({self._refused[held]}); frames after a refused one are not folded")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise FrameOutOfOrder(FIELD, f"frame {index} waited {wait_s:g} s for frame {held}, which did not "
                                             "come; send the frames before it first")
            self._turn.wait(remaining)

    def check_turn(self, index: int, held: int) -> None:
        """Refuse a frame whose place the session's stream has passed (it holds ``held`` frames)."""
        self._refused.pop(index, None)  # sent again: its turn, whatever became of it before
        if index != held:
            raise FrameOutOfOrder(FIELD, f"frame {index} comes too late: the session holds {held} frames, so the "
                                         f"next one is frame {held}")

    def refused(self, index: int | None, why: BaseException) -> None:
        """The frame at ``index`` was refused: the frames waiting behind it give up."""
        if index is not None:
            self._refused[index] = str(why)[:200]
            self._turn.notify_all()

    def folded(self, held: int) -> None:
        """A frame was folded (the session holds ``held`` frames now): wake the frames waiting."""
        self._refused = {i: why for i, why in self._refused.items() if i >= held}
        self._turn.notify_all()
