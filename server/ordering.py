"""The order a session folds numbered frames in: their ``Frame-Index``, not their arrival.

A client that keeps several frames in flight (`client.sdk.Session.add_frames`) numbers them with their
place in the session's stream. Requests on different connections may reach the session in any order,
so a decoded and validated frame waits, on the event loop and outside the job queue (a waiting frame
holds no compute slot that the frame it waits for needs), until the session holds exactly the frames
before it; it is folded then, and the fold checks its place again under the session's lock. The
scene is the one that posting the frames one by one gives, run after run. A frame whose turn does
not come is refused instead of folded out of order: when the frame at the gap was refused (the
stream stops there), when a correction took frames out of the session (the frames in flight were
numbered for the stream it had before), or when no frame is folded for the wait. A waiting frame
also ends when its session is deleted or the service stops (``check``, polled every `CHECK_S`).
Frames without an index fold in arrival order, as before.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Iterator
from contextlib import contextmanager
from typing import Callable

from .session_errors import FrameOutOfOrder, FramesAhead

FIELD = "Frame-Index"
# numbered frames of one session read (or being read) ahead of their turn: each holds its decoded
# arrays and its begun fold while it waits outside any job queue, so they are bounded; a client keeps
# a few in flight (the SDK 3), one past the bound gets 429 and comes again
MAX_AHEAD = 16
CHECK_S = 1.0  # a waiting frame looks this often whether it is still wanted (its session deleted, the service stopping)


class FrameOrder:
    """The turns of one session's numbered frames: waited for on event loops (`wait_turn`), moved on
    from the threads that fold or correct (`folded`, `refused`, `recounted`, `check_turn`, under the
    session's lock)."""

    def __init__(self):
        self._mutex = threading.Lock()  # the waiters and the refusals, shared by the loop and the fold threads
        self._waiters: list[tuple[asyncio.AbstractEventLoop, asyncio.Future]] = []
        # stream place -> why no numbered frame will fold there (the end of a message that begins
        # "frame N "): the frames numbered after it give up until a frame takes that place
        self._refused: dict[int, str] = {}
        self._ahead = 0  # numbered frames read or waiting, not yet folding (`ahead`)

    async def wait_turn(self, index: int, frames: Callable[[], int], wait_s: float,
                        check: Callable[[], None] = lambda: None,
                        left: Callable[[], Awaitable[None]] | None = None) -> None:
        """Return once ``frames()`` (the session's frame count) is ``index`` or more; raise
        `FrameOutOfOrder` when the place before it will not be filled (the frame there was refused,
        or a correction took frames out of the session), or when no frame is folded for ``wait_s``
        (a long pipeline that moves on keeps its frames waiting). ``check()`` raises where the frame
        is no longer wanted (its session deleted, the service stopping), and ``left()`` where its
        client closed the connection (the frame was never answered: it holds no place then); they run
        at each wake and every `CHECK_S`, as nothing wakes a waiter for those."""
        loop = asyncio.get_running_loop()
        deadline, last = time.monotonic() + wait_s, frames()
        while (held := frames()) < index:
            check()
            if left is not None:
                await left()
            if held != last:
                deadline, last = time.monotonic() + wait_s, held
            woken = loop.create_future()
            with self._mutex:
                why = self._refused.get(held)
                self._waiters.append((loop, woken))
            if why is not None:
                raise FrameOutOfOrder(FIELD, f"frame {index} {why}")
            if frames() != held:  # folded between the check and the registration
                continue
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise FrameOutOfOrder(FIELD, f"frame {index} waited {wait_s:g} s for frame {held}, which did not "
                                             "come; send the frames before it first")
            try:
                await asyncio.wait_for(woken, min(remaining, CHECK_S))
            except TimeoutError:
                with self._mutex:  # a waiter that looks again is not left registered once per look
                    if (loop, woken) in self._waiters:
                        self._waiters.remove((loop, woken))

    @contextmanager
    def ahead(self, index: int, held: int) -> Iterator[None]:
        """Count numbered frame ``index`` (the session holds ``held``) from before it is read until its
        turn came (or it was refused); `FramesAhead` where `MAX_AHEAD` are already, unless it is the
        next one (or one too late, refused as such): the frames waiting for it would otherwise wait
        in vain."""
        with self._mutex:
            if self._ahead >= MAX_AHEAD and index > held:
                raise FramesAhead(FIELD, f"{MAX_AHEAD} numbered frames of this session are already read ahead of their "
                                         "turn; send it again once the frames before it are folded")
            self._ahead += 1
        try:
            yield
        finally:
            with self._mutex:
                self._ahead -= 1

    def check_turn(self, index: int, held: int) -> None:
        """Refuse a frame that is not next in the session's stream (it holds ``held`` frames): one
        whose place the stream has passed, or one numbered for frames that a correction took out."""
        with self._mutex:
            if index == held:
                self._refused.pop(index, None)  # sent again: its turn, whatever became of it before
                return
            why = self._refused.get(held)
        if index < held:
            raise FrameOutOfOrder(FIELD, f"frame {index} comes too late: the session holds {held} frames, so the "
                                         f"next one is frame {held}")
        # its turn had come: the session's count went down since (a correction, or a fold undone)
        raise FrameOutOfOrder(FIELD, f"frame {index} " + (why or _fewer(held)))

    def refused(self, index: int | None, why: BaseException) -> None:
        """The frame at ``index`` was refused: the frames waiting behind it give up."""
        if index is not None:
            with self._mutex:
                self._refused[index] = (f"follows frame {index}, which was refused ({str(why)[:200]}); frames after "
                                        "a refused one are not folded")
            self._wake()

    def recounted(self, before: int, after: int) -> None:
        """A correction made the session's ``before`` frames ``after``: the frames waiting look again.
        Where it took frames out, the numbered frames in flight were numbered for the longer stream:
        they and those sent after them are refused, until a frame takes place ``after``."""
        if after < before:
            with self._mutex:
                self._refused = {i: why for i, why in self._refused.items() if i < after}
                self._refused[after] = (f"cannot be folded in its place: a correction removed frames after it was "
                                        f"numbered (the session's frame count went from {before} to {after}), so the "
                                        f"next one is frame {after}")
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


def _fewer(held: int) -> str:
    return (f"cannot be folded in its place: the session's frame count went down to {held} while it was in flight "
            f"(a fold was undone), so the next one is frame {held}")


def _set(future: asyncio.Future) -> None:
    if not future.done():  # a waiter that timed out meanwhile
        future.set_result(None)
