"""The order a session folds numbered frames in: their ``Frame-Index``, not their arrival.

A client that keeps several frames in flight (`client.sdk.Session.add_frames`) numbers them with their
place in the session's stream. Requests on different connections may reach the session in any order,
so a decoded and validated frame waits, on the event loop and outside the job queue (a waiting frame
holds no compute slot that the frame it waits for needs), until the session holds exactly the frames
before it; it is folded then, and the fold checks its place again under the session's lock. The
scene is the one that posting the frames one by one gives, run after run. A frame whose turn does
not come is refused instead of folded out of order: when the frame at the gap was refused (the
stream stops there), or when no frame is folded for the wait. Frames without an index fold in
arrival order, as before.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Callable

from .session_errors import FrameOutOfOrder

FIELD = "Frame-Index"


class FrameOrder:
    """The turns of one session's numbered frames: waited for on event loops (`wait_turn`), moved on
    from the threads that fold (`folded`, `refused`, `check_turn`, under the session's lock)."""

    def __init__(self):
        self._mutex = threading.Lock()  # the waiters and the refusals, shared by the loop and the fold threads
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future]] = []
        self._refused: dict[int, str] = {}  # index -> why the frame with that index was refused

    async def wait_turn(self, index: int, frames: Callable[[], int], wait_s: float) -> None:
        """Return once ``frames()`` (the session's frame count) is ``index`` or more; raise
        `FrameOutOfOrder` when the frame at the gap was refused, or when no frame is folded for
        ``wait_s`` (a long pipeline that moves on keeps its frames waiting)."""
        loop = asyncio.get_running_loop()
        deadline, last = time.monotonic() + wait_s, frames()
        while (held := frames()) < index:
            if held != last:
                deadline, last = time.monotonic() + wait_s, held
            woken = loop.create_future()
            with self._mutex:
                why = self._refused.get(held)
                self._waiters.append((loop, woken))
            if why is not None:
                raise FrameOutOfOrder(FIELD, f"frame {index} follows frame {held}, which was refused ({why}); "
                                             "frames after a refused one are not folded")
            if frames() != held:  # folded between the check and the registration
                continue
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise FrameOutOfOrder(FIELD, f"frame {index} waited {wait_s:g} s for frame {held}, which did not "
                                             "come; send the frames before it first")
            try:
                await asyncio.wait_for(woken, remaining)
            except TimeoutError:
                pass

    def check_turn(self, index: int, held: int) -> None:
        """Refuse a frame whose place the session's stream has passed (it holds ``held`` frames)."""
        with self._mutex:
            self._refused.pop(index, None)  # sent again: its turn, whatever became of it before
        if index != held:
            raise FrameOutOfOrder(FIELD, f"frame {index} comes too late: the session holds {held} frames, so the "
                                         f"next one is frame {held}")

    def refused(self, index: int | None, why: BaseException) -> None:
        """The frame at ``index`` was refused: the frames waiting behind it give up."""
        if index is not None:
            with self._mutex:
                self._refused[index] = str(why)[:200]
            self._wake()

    def folded(self, held: int) -> None:
        """A frame was folded (the session holds ``held`` frames now): wake the frames waiting."""
        with self._mutex:
            self._refused = {i: why for i, why in self._refused.items() if i >= held}
        self._wake()

    def _wake(self) -> None:
        with self._mutex:
            waiters, self._waiters = self._waiters, []
        for loop, woken in waiters:
            try:
                loop.call_soon_threadsafe(_set, woken)
            except RuntimeError:  # its loop closed (the service stopped): nobody waits there any more
                pass


def _set(future: asyncio.Future) -> None:
    if not future.done():  # a waiter that timed out meanwhile
        future.set_result(None)
