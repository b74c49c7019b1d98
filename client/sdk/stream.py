"""A session's frames with several in flight (`Session.add_frames`): each frame's body is built on a
worker, posted with its place in the session's stream once the frames before it were built, and
answered in order.

Posting a frame only after the bodies before it were built means that a frame the client cannot send
(a malformed argument, a frame its checks refuse) stops the stream before any frame after it goes:
the service would otherwise hold those, numbered for places that no frame fills, until its
``frame_order_wait_s`` ran out.
"""

from __future__ import annotations

import collections
import itertools
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TYPE_CHECKING, Iterable, Iterator

from .errors import CanonicalError, StreamRefused, StreamStopped

if TYPE_CHECKING:
    from .session import Session


class _NotSent(Exception):
    """A frame not posted because one before it could not be built (that frame's error stops the stream)."""


def _built_then_sent(session: "Session", frame: dict, index: int, before: Future | None, built: Future) -> dict:
    """Build ``frame``'s body (beside the others' builds), then post it at ``index`` once every frame
    before it was built (``before``, which stands for them all: a failure is passed down the chain)."""
    try:
        prepared = session._frame_body(frame)
    except BaseException as exc:
        built.set_exception(exc)
        raise
    if before is not None and before.exception() is not None:  # waits for it; it stops the stream
        built.set_exception(_NotSent())
        raise _NotSent()
    built.set_result(None)
    return session._send_frame(*prepared, index)


def _replayed(session: "Session", frame: dict, first: Future) -> dict:
    """A frame whose ``frame_id`` an earlier frame of the same stream carries: posted once that one is
    answered, without a place (the service answers it from the frame it holds: a replay, or 409 where
    its content differs), so that it takes no place in the stream."""
    first.result()
    return session._send_frame(*session._frame_body(frame), None)


def stream_frames(session: "Session", frames: Iterable[dict], in_flight: int, first_index: int | None) -> Iterator[dict]:
    """`Session.add_frames`: the reports of ``frames`` in order, up to ``in_flight`` of them at once."""
    index = session.stats()["frames"] if first_index is None else int(first_index)
    pool = ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="canonical-frames")
    # (future, its place in the stream, its frame_id, whether it takes that place: not a repeated frame_id)
    pending: collections.deque = collections.deque()
    first_of: dict[str, tuple[Future, int]] = {}  # frame_id -> the first frame of this stream that carries it
    acknowledged, alone, stopped, built = 0, True, False, None
    try:
        for frame in itertools.chain(frames, [None]):
            if frame is not None:
                frame_id = None if frame.get("frame_id") is None else str(frame["frame_id"])
                if frame_id in first_of:
                    first, place = first_of[frame_id]
                    pending.append((pool.submit(_replayed, session, frame, first), place, frame_id, False))
                else:
                    before, built = built, Future()
                    future = pool.submit(_built_then_sent, session, frame, index, before, built)
                    pending.append((future, index, frame_id, True))
                    if frame_id is not None:
                        first_of[frame_id] = future, index
                    index += 1
            # alone: where an earlier stream's frame was refused, the frames after it are refused
            # until a frame takes its place; and a frame the session holds takes none
            while pending and (frame is None or len(pending) >= (1 if alone else in_flight)):
                future, place, frame_id, takes_place = pending[0]
                try:
                    report = future.result()
                except CanonicalError as exc:
                    stopped = True
                    raise StreamRefused(exc, place, acknowledged) from exc
                except Exception as exc:  # the client could not send it (its arguments, the connection)
                    stopped = True
                    raise StreamStopped(exc, place, acknowledged) from exc
                pending.popleft()
                acknowledged += 1
                misnumbered = False
                if takes_place and report.get("frame_index", place) < place:  # held already: takes no place
                    index -= 1
                    # frames posted after it mid-stream were numbered for the place it did not take
                    misnumbered = stopped = not alone and any(later for *_, later in pending)
                elif takes_place:
                    alone = False
                yield report
                if misnumbered:
                    raise StreamStopped(ValueError(
                        f"frame_id {frame_id!r}: the session holds it already (its frame {report['frame_index']}), so it "
                        f"took no place, and the frames sent after it were numbered one place too far; send them "
                        f"again with first_index={place}"), place, acknowledged)
    finally:
        # frames not yet posted are dropped; posted ones finish (the service answers them, in order),
        # but not after a stop: the frames behind a stopped one are not folded, and waiting for their
        # answers would hold the caller until the service gives up on them
        pool.shutdown(wait=not stopped, cancel_futures=True)
