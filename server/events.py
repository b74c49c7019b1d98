"""Fold events for live clients (the web viewer) and the track of input cameras they show.

`FoldEvents` lives on the event loop: the frames route calls `FoldEvents.folded` after a fold is
acknowledged, and every open event stream of that session gets the event (frame counts, the fold
report, the frame's camera), encoded once for all of them. Publishing never waits on a subscriber:
each has a bounded queue, and one whose queue is full has fallen behind and is dropped (its stream
ends with a ``dropped`` event; the viewer reconnects and gets the latest state). Open streams are
capped per session and per service, so the fan-out a fold pays for is bounded. A stream may ask for
at most one event per interval (`FoldBatch`): a page that redraws a few times a second has no use
for each of a 30 Hz stream's folds, and every event costs the browser a wake-up and a parse.

The input cameras a stream shows are the session's camera track (`track`): each fold event
carries its frame's camera, and `FoldEvents.track` reads the whole track for a page that opens.
"""

from __future__ import annotations

import asyncio
import json
import signal
import time
import weakref
from collections import defaultdict
from typing import NamedTuple

from canonical_core import Camera

from .track import CAMERAS_FILE, camera_json, camera_row, read_track


def sse(event: str, data: dict) -> bytes:
    """One Server-Sent Event."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


class Published(NamedTuple):
    """An event on a stream's queue: its fields (None for `DROPPED`) and its encoding, made once for
    every stream that sends it as it is."""

    event: dict | None
    data: bytes


DROPPED = Published(None, sse("dropped", {"reason": "the stream fell behind"}))  # a stream's last event


class FoldBatch:
    """The fold events a stream has not sent yet, merged into one (a stream with at most one event
    per interval): the latest fold's fields, plus ``folds`` (how many folds it stands for),
    ``cameras`` (theirs, oldest first, so no input camera is missed), ``previous_time`` (the time of
    the fold before the latest, sent or not: the gap the stream of frames has, not the interval's;
    None for the first fold the stream sees) and ``warned`` (the latest of them whose report had
    warnings, as ``{"frame_index", "warnings"}``, else None: advice is not lost with the folds it
    came with).

    Example:
        >>> batch = FoldBatch()
        >>> for k, warnings in enumerate([[], ["depth under the working range"], []]):
        ...     batch.add({"type": "fold", "time": 10.0 + k, "frames": k + 1, "camera": {"frame_index": k},
        ...                "report": {"frame_index": k, "warnings": warnings}})
        >>> event = batch.take()
        >>> event["frames"], event["folds"], [c["frame_index"] for c in event["cameras"]], event["previous_time"]
        (3, 3, [0, 1, 2], 11.0)
        >>> event["warned"]
        {'frame_index': 1, 'warnings': ['depth under the working range']}
        >>> batch.take() is None
        True
    """

    def __init__(self) -> None:
        self._pending: dict | None = None
        self._last_time: float | None = None  # of the last fold added, taken or not

    @property
    def pending(self) -> bool:
        """Whether folds were added since the last take."""
        return self._pending is not None

    def add(self, fold: dict) -> None:
        pending = self._pending or {"folds": 0, "cameras": [], "warned": None}
        warnings = fold["report"].get("warnings")
        self._pending = {
            **fold,
            "folds": pending["folds"] + 1,
            "cameras": [*pending["cameras"], fold["camera"]],
            "previous_time": self._last_time,
            "warned": {"frame_index": fold["report"]["frame_index"], "warnings": warnings} if warnings else pending["warned"],
        }
        self._last_time = fold["time"]

    def take(self) -> dict | None:
        """The merged event of the folds added since the last take; None if there are none."""
        event, self._pending = self._pending, None
        return event


class TooManyStreams(Exception):
    """An event stream over a cap; ``setting`` names the cap."""

    def __init__(self, message: str, setting: str):
        super().__init__(message)
        self.setting = setting


class FoldEvents:
    """Per-session fan-out of fold events to bounded asyncio queues, and the sessions' camera tracks.

    A stream holds its slot from `subscribe` until `unsubscribe` (its end), dropped or not, so the
    caps bound open connections too.

    Example:
        >>> events = FoldEvents(per_session=1, total=8, queue_size=1)
        >>> queue = events.subscribe("s")
        >>> events.subscribe("s")
        Traceback (most recent call last):
        ...
        server.events.TooManyStreams: events: session s has 1 open event streams, the limit (max_event_streams_per_session)
        >>> events.publish("s", {"type": "fold"}); events.publish("s", {"type": "fold"})
        >>> [queue.get_nowait() == DROPPED, events.subscribers("s")]
        [True, 0]
    """

    def __init__(self, per_session: int = 32, total: int = 256, queue_size: int = 32):
        self.per_session, self.total, self.queue_size = per_session, total, queue_size
        self._subscribers: dict[str, set[asyncio.Queue]] = defaultdict(set)  # those that keep up
        self._open: dict[str, int] = defaultdict(int)  # open streams per session, dropped ones included
        self.dropped = 0  # streams dropped for falling behind, since start
        # session -> unix time of its last acknowledged fold; a deleted session's entry goes with it
        self.last_fold: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.closing = asyncio.Event()  # set when the service begins to stop: open streams end

    def close_streams_on_exit(self) -> None:
        """Chain SIGINT / SIGTERM so that open event streams end when the server is told to stop.

        A graceful shutdown waits for responses in progress, and an event stream never finishes on
        its own; call this on the event loop after the server installed its handlers (at startup)."""
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous = signal.getsignal(sig)
            if not callable(previous):
                continue

            def handler(signum, frame, previous=previous):
                loop.call_soon_threadsafe(self.closing.set)
                previous(signum, frame)

            try:
                signal.signal(sig, handler)
            except ValueError:  # not the main thread (an in-process test client): no signals to chain
                return

    def subscribe(self, session_id: str) -> asyncio.Queue:
        """A new stream's queue of `Published` events; `TooManyStreams` over a cap."""
        if self._open[session_id] >= self.per_session:
            raise TooManyStreams(f"events: session {session_id} has {self._open[session_id]} open event streams, "
                                 "the limit (max_event_streams_per_session)", "max_event_streams_per_session")
        if self.open_streams() >= self.total:
            raise TooManyStreams(f"events: the service has {self.total} open event streams, the limit "
                                 "(max_event_streams)", "max_event_streams")
        queue: asyncio.Queue = asyncio.Queue(self.queue_size)
        self._open[session_id] += 1
        self._subscribers[session_id].add(queue)
        return queue

    def unsubscribe(self, session_id: str, queue: asyncio.Queue) -> None:
        """The stream ended: its slot is free."""
        self._drop(session_id, queue)
        self._open[session_id] -= 1
        if self._open[session_id] <= 0:
            del self._open[session_id]

    def _drop(self, session_id: str, queue: asyncio.Queue) -> None:
        queues = self._subscribers.get(session_id)
        if queues is not None:
            queues.discard(queue)
            if not queues:
                del self._subscribers[session_id]

    def open_streams(self) -> int:
        return sum(self._open.values())

    def subscribers(self, session_id: str) -> int:
        """The session's streams that keep up (those a fold publishes to)."""
        return len(self._subscribers.get(session_id, ()))

    def publish(self, session_id: str, event: dict) -> None:
        """Put ``event`` (encoded once) on every subscriber's queue; a subscriber whose queue is full is
        dropped: its queue then holds only `DROPPED`, and no fold publishes to it again."""
        data = Published(event, sse(event["type"], event))
        for queue in list(self._subscribers.get(session_id, ())):
            if queue.full():
                self._drop(session_id, queue)
                self.dropped += 1
                while not queue.empty():
                    queue.get_nowait()
                queue.put_nowait(DROPPED)
            else:
                queue.put_nowait(data)

    def folded(self, session, camera: Camera, report) -> None:
        """After an acknowledged fold (the session has added its camera to its track): tell the
        session's subscribers."""
        now = time.time()
        self.last_fold[session] = now
        camera = camera_json(camera_row(report.frame_index, camera))
        frames, voxels = session.counts()
        self.publish(session.id, {"type": "fold", "time": now, "frames": frames,
                                  "voxels": voxels, "report": report.to_dict(), "camera": camera})

    def track(self, session, since: int = 0) -> list[dict]:
        """The session's input cameras from frame ``since`` on, oldest first."""
        rows = read_track(session.path / CAMERAS_FILE, session.counts()[0])
        return [camera_json(r) for r in rows[rows[:, 0] >= since]]

    def last_fold_time(self, session) -> float | None:
        """Unix time of the last fold: known since start, else the camera file's mtime, else None."""
        if session in self.last_fold:
            return self.last_fold[session]
        try:
            return (session.path / CAMERAS_FILE).stat().st_mtime
        except OSError:
            return None
