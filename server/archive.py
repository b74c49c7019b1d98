"""The frame archive of one session: the frames it folded, kept so that poses can be corrected and
frames removed after the fact (`Scene.refolded` of the corrected stream).

File ``archive.log`` in the session folder, in the frame log's record format (`server.framelog`:
magic, length, index, CRCs, payload; ``index`` is the record's number), appended and fsynced.
Each payload is a msgpack map of one of three kinds:

- a frame: ``{"arrival", "frame_id", "digest", "message"}``: its arrival index, the client's
  frame_id, the digest of its wire payload (to recognise a retry), and its wire payload as it
  arrived (`compress_payload`): the bytes the client sent where its images came compressed (PNG or
  JPEG colour, depth as a PNG or a zstandard array), else zstandard over them; archives written
  before read back too (an 8-bit colour array as PNG, zlib over the map); None where the retention
  setting did not keep it;
- a correction: ``{"poses": {arrival: 16 numbers, row-major c2w}, "removed": [arrival, ...],
  "first": the stream position of the first frame it touches, "id": the id of a background
  correction or None}``;
- an undo: ``{"undoes": a background correction's id, "error": why}``: its re-fold failed, and the
  state is again as before it (`append_undo`).

The archive's state is the replay of its records in order: the frames the scene holds, in fold
order, each with its current pose. A correction is archived (the commit point) before it is
acknowledged.

Frames are archived off the acknowledged path. A folded frame is durable in the session's frame log
(fsynced before the answer); compressing and appending it (a second fsync) need not delay the answer,
so `defer_frame` queues it and a writer thread of the archive compresses and appends it. The frame log is not restarted
while the archive lacks frames (`flush` comes first), so after a crash the frames the archive lacks
are all in the log, and the restart archives them from there (`durability.restore_session`). Whatever
reads the archive's frames (a correction) flushes it first.

Retention (`Retention`): ``all`` keeps every frame; ``keyframes`` keeps one frame in
`KEYFRAME_EVERY` (by arrival index), and a correction re-folds those alone, so the other frames
leave the scene at the first correction; ``none`` keeps no archive and refuses corrections.
"""

from __future__ import annotations

import errno
import mmap
import os
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Literal

import msgpack
import numpy as np

from canonical_core import Frame
from canonical_core.scene.corrections import FrameRef

from . import wire
from .digests import payload_digest
from .framelog import FrameLog, LogWedged, Record, StorageError, scan
from .payloads import ARCHIVE, compress_payload, decompress_message, decompress_payload

KEYFRAME_EVERY = 5  # retention "keyframes": frames whose arrival index is a multiple of this are kept
Retention = Literal["all", "keyframes", "none"]
RETENTIONS = ("all", "keyframes", "none")


def archive_failure(exc: Exception) -> str:
    """The archive's `problem` after a frame could not be archived."""
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else f"{type(exc).__name__}: {exc}"
    return f"{ARCHIVE}: a frame could not be archived ({reason}); corrections are refused until a restart"


class ArchiveClosed(Exception):
    """The archive was closed (its session deleted, or the service stopping) while something still
    read it: a background re-fold then stops."""


@dataclass(frozen=True)
class Entry:
    """One frame the scene holds: where its archive record is, and what names it."""

    arrival: int
    frame_id: str | None
    digest: str
    offset: int  # of the record's payload in the file
    length: int
    kept: bool  # whether its message is in the archive (retention)


def _mapped(path: Path) -> bytes | mmap.mmap:
    """The archive's bytes mapped rather than read: it holds every frame its session kept (hundreds of
    kilobytes each, gigabytes in a long session), which a start scans once, record by record."""
    if not path.is_file() or path.stat().st_size == 0:
        return b""
    with open(path, "rb") as f:
        mapped = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    mapped.madvise(mmap.MADV_SEQUENTIAL)
    return mapped


class SessionArchive:
    """An open archive: its file, appended by one writer (the session's lock), and its replayed state."""

    def __init__(self, path: Path, retention: Retention):
        if retention not in RETENTIONS:
            raise ValueError(f"archive_retention: expected one of {list(RETENTIONS)}, got {retention!r}")
        self.path, self.retention = path, retention
        self.entries: list[Entry] = []
        self.poses: dict[int, list[float]] = {}  # arrival -> corrected c2w (16 numbers)
        self.corrections = 0
        self.firsts: list[int] = []  # per correction: the stream position of the first frame it touched
        # of the background corrections archived: what each did (its answer's counts), for its status
        self.corrections_done: dict[str, dict] = {}  # or {"failed": why}, for one undone
        # the latest background correction: its id, the entries it removed and the poses it replaced
        self._before_background: tuple[str, list[Entry], dict[int, list[float] | None]] | None = None
        self.next_arrival = 0
        self._records: list[tuple[int, bool]] = []  # (file offset, is a frame) of every record
        self.problem: str | None = None  # why corrections cannot be served (a damaged or incomplete archive)
        self.problem_errno = errno.EIO  # the OSError's number where a write failed (a full disk: ENOSPC)
        found = scan(_mapped(path))
        for record in found.records:
            self._apply(record)
        if found.damaged:
            self.problem = f"{ARCHIVE}: {found.describe()}; corrections are refused (the scene itself is served)"
        torn, end = found.torn, found.end
        del found  # its records' payloads are views of the mapping, which goes with them
        self._log = FrameLog(path)  # appends: written, fsynced, cut back on failure, as the frame log's
        self._fd = os.open(path, os.O_RDONLY)  # reads of archived messages
        # held by each read and by `close`: a read never sees the descriptor closed under it, nor its
        # number reused by another file
        self._reading = threading.Lock()
        self._queue: queue.Queue = queue.Queue()  # frames deferred to the writer: (frame_id, digest, payload)
        self._writer: threading.Thread | None = None
        if torn:
            self._log.truncate(end)

    # -- state ------------------------------------------------------------------------------------
    def _apply(self, record: Record) -> None:
        body = msgpack.unpackb(record.payload, strict_map_key=False)
        self._records.append((record.offset, "arrival" in body))
        if "arrival" in body:
            message = body["message"] or b""
            # the message is the map's last value, so its bytes end the payload: read back alone later
            offset = record.end - len(message)
            self.entries.append(Entry(body["arrival"], body["frame_id"], body["digest"], offset, len(message),
                                      body["message"] is not None))
            self.next_arrival = max(self.next_arrival, body["arrival"] + 1)
            return
        if "undoes" in body:
            self._undo(body["undoes"], body["error"])
            return
        gone = set(body["removed"])
        self._before_background = None  # what the latest correction changed, if a background one: should it fail
        if body.get("id") is not None:
            touched = gone | {int(a) for a in body["poses"]}
            self._before_background = (body["id"], [e for e in self.entries if e.arrival in gone],
                                       {a: self.poses.get(a) for a in touched})
        self.entries = [e for e in self.entries if e.arrival not in gone]
        self.poses = {a: p for a, p in self.poses.items() if a not in gone} | {int(a): p for a, p in body["poses"].items()}
        self.firsts.append(body.get("first", 0))
        if body.get("id") is not None:  # archives written before the counts were kept: those of the record
            self.corrections_done[body["id"]] = body.get("summary") or {
                "corrected": len(set(body["poses"]) - gone), "removed": len(gone), "dropped": 0}
        self.corrections += 1

    def _undo(self, correction_id: str, error: str) -> None:
        """The state as if the background correction ``correction_id`` (the latest correction: no other
        is taken while one re-folds) had never been archived; the frames archived since stay."""
        if self._before_background is None or self._before_background[0] != correction_id:
            self.problem = f"{ARCHIVE}: it undoes correction {correction_id}, not its latest; corrections are refused"
            return
        _, removed, poses = self._before_background
        self.entries = sorted(self.entries + removed, key=lambda e: e.arrival)  # entries are in arrival order
        for arrival, pose in poses.items():
            if pose is None:
                self.poses.pop(arrival, None)
            else:
                self.poses[arrival] = pose
        self.firsts.pop()
        self.corrections -= 1
        self.corrections_done[correction_id] = {"failed": error}
        self._before_background = None

    @property
    def background_correction(self) -> str | None:
        """The id of a background correction that is the archive's latest correction and not undone."""
        return None if self._before_background is None else self._before_background[0]

    def status(self, correction_id: str, session_id: str, frames: int) -> dict | None:
        """The status of a background correction this archive holds, as a restart left it (None for
        one it does not): done, with the counts it was answered with and the session's ``frames``
        now, or failed, with why."""
        counts = self.corrections_done.get(correction_id)
        if counts is None:
            return None
        if "failed" in counts:
            return {"correction_id": correction_id, "state": "failed", "refolded": 0, "total": 0,
                    "error": counts["failed"], "result": None}
        result = {"frames_before": frames + counts["removed"] + counts["dropped"], **counts, "id": session_id,
                  "frames": frames, "state": "done", "correction_id": correction_id}
        return {"correction_id": correction_id, "state": "done", "refolded": 0, "total": 0, "error": None,
                "result": result}

    def refs(self) -> list[FrameRef]:
        return [FrameRef(e.arrival, e.frame_id) for e in self.entries]

    def nbytes(self) -> int:
        return self._log.size()

    def frames(self, entries: list[Entry]) -> Iterator[Frame | None]:
        """The frames of ``entries`` in order, each with its current pose (None where not kept); lazy,
        so a re-fold holds one decoded frame at a time."""
        for msg in self.messages(entries):
            yield None if msg is None else wire.frame_from_message(msg)

    def messages(self, entries: list[Entry]) -> Iterator[dict | None]:
        """The wire messages of ``entries`` in order, each with its current pose (None where not kept)."""
        for e in entries:
            yield None if not e.kept else self._message(e, decompress_message(self._read(e.length, e.offset), e.digest))

    def payloads(self, entries: list[Entry]) -> Iterator[bytes | None]:
        """The wire payloads of ``entries`` in order (None where not kept), as the frame log holds them: as
        they arrived, or, for a frame whose pose a correction changed, its message with that pose packed
        again (what the correction logged)."""
        for e in entries:
            if not e.kept:
                yield None
                continue
            payload = decompress_payload(self._read(e.length, e.offset), e.digest)
            yield payload if e.arrival not in self.poses else wire.pack(self._message(e, wire.unpack(payload)))

    def _read(self, length: int, offset: int) -> bytes:
        with self._reading:
            if self._fd < 0:
                raise ArchiveClosed(f"{ARCHIVE}: closed (its session was deleted, or the service is stopping)")
            return os.pread(self._fd, length, offset)

    def _message(self, e: Entry, msg: dict) -> dict:
        if e.arrival in self.poses:
            msg["c2w"] = np.asarray(self.poses[e.arrival], np.float64).reshape(4, 4).tolist()
        return msg

    # -- writing ----------------------------------------------------------------------------------
    def keeps(self, arrival: int) -> bool:
        return self.retention == "all" or (self.retention == "keyframes" and arrival % KEYFRAME_EVERY == 0)

    def append_frame(self, frame_id: str | None, digest: str, payload: bytes) -> None:
        """Archive the next frame, its wire payload (fsynced); `cut` takes it back if it is not folded."""
        arrival = self.next_arrival
        body = {"arrival": arrival, "frame_id": frame_id, "digest": digest,
                "message": compress_payload(payload) if self.keeps(arrival) else None}
        self._append(msgpack.packb(body))

    def defer_frame(self, frame_id: str | None, digest: str, payload: bytes) -> None:
        """Archive the next frame (its wire payload) from the writer thread, off the caller's path;
        `flush` waits for it. The caller keeps the frame durable meanwhile (the frame log)."""
        if self._writer is None:
            self._writer = threading.Thread(target=self._write_deferred, name=f"archive-{self.path.parent.name}",
                                            daemon=True)
            self._writer.start()
        self._queue.put((frame_id, digest, payload))

    def keep_folded(self, frame_id: str | None, digest: str, payload: bytes, at_once: bool) -> None:
        """Archive a folded frame: off the acknowledged path (`defer_frame`: the session's frame log
        holds it durably until the archive does; a failure leaves it there and corrections refused
        (`problem`) until a restart archives it from the log), but ``at_once`` while a background
        correction re-folds: the corrected scene that replaces the served one is made of the
        archive's frames, so a frame the archive cannot take raises `StorageError` (`check_at_once`),
        and the caller takes the frame back instead of acknowledging it."""
        if not at_once:
            if self.problem is None:
                self.defer_frame(frame_id, digest, payload)
            return
        self.check_at_once()
        self.flush()
        try:
            self.append_frame(frame_id, digest, payload)
        except Exception as exc:  # noqa: BLE001 - any failure: the frame is not archived
            self._write_failed(exc)
        self.check_at_once()

    def check_at_once(self) -> None:
        """Raise `StorageError` while the archive cannot take frames at once (`problem`): a frame
        folded during a background correction would not be in the scene it swaps in."""
        if self.problem is not None:
            raise StorageError("frame", OSError(self.problem_errno, f"{self.problem}; frames are refused until the "
                                                                    "background correction ends"))

    def _write_failed(self, exc: Exception) -> None:
        self.problem = archive_failure(exc)
        self.problem_errno = exc.errno if isinstance(exc, OSError) and exc.errno else errno.EIO

    def flush(self) -> None:
        """Wait until every deferred frame is archived (or the archive has a `problem`)."""
        self._queue.join()

    def _write_deferred(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if self.problem is None:
                    frame_id, digest, payload = item
                    try:
                        self.append_frame(frame_id, digest, payload)
                    except Exception as exc:  # noqa: BLE001 - the frame stays in the frame log; a restart archives it
                        self._write_failed(exc)
            finally:
                self._queue.task_done()

    def append_correction(self, poses: dict[int, np.ndarray], removed: list[int], first: int = 0,
                          correction_id: str | None = None, summary: dict | None = None) -> None:
        """Archive a correction (fsynced): the commit point of `Corrections.correct`. ``first``: the stream
        position of the first frame it touches (the states of the frames before it stay valid);
        ``correction_id``: a background correction's id, by which a restart knows it done, and
        ``summary`` the counts its answer gives (corrected, removed, dropped, frames_before)."""
        body = {"poses": {a: np.asarray(c2w, np.float64).reshape(16).tolist() for a, c2w in poses.items()},
                "removed": sorted(removed), "first": first, "id": correction_id, "summary": summary}
        self._append(msgpack.packb(body))

    def append_undo(self, correction_id: str, error: str) -> None:
        """Archive that the background correction ``correction_id`` failed (fsynced): its re-fold could
        not be made, so the archive is again what the served scene holds (`_undo`), and a restart
        neither retries it nor counts it."""
        self._append(msgpack.packb({"undoes": correction_id, "error": error}))

    def _append(self, payload: bytes) -> None:
        try:
            offset = self._log.append(len(self._records), payload)
        except LogWedged:
            self.problem = f"{ARCHIVE}: a failed append could not be cut back; corrections are refused until a restart"
            raise
        self._apply(Record(offset, len(self._records), payload, checkpoint=False))

    def fence(self, lease) -> None:
        """Fence this archive's appends and cuts by an owner's lease (`server.cluster.lease.Lease`)."""
        self._log.lease = lease

    def cut(self, frames: int = 1, aside: Callable[[bytes], object] | None = None) -> None:
        """Remove the last ``frames`` (at least one) records, frames' that the scene does not hold (not
        folded, or dropped by a repair); ``aside`` gets their bytes first (to keep a copy)."""
        records = self._records[-frames:]
        if len(records) != frames or not all(is_frame for _, is_frame in records):
            raise ValueError(f"archive: the last {frames} records are not all frames")
        offset = records[0][0]
        if aside is not None:
            aside(self._read(self._log.size() - offset, offset))
        self._log.truncate(offset)
        del self._records[-frames:]
        self.next_arrival = self.entries[-frames].arrival
        del self.entries[-frames:]

    def cut_to(self, frames: int, logged: dict[int, bytes] | None = None) -> None:
        """Make the archive hold ``frames`` frames, the scene's count after a restart. Frames it lacks
        (deferred, not yet written when the service stopped) are archived from ``logged`` (stream
        position -> wire payload: the frame log's records). One frame archived but never folded (an
        archive written before frames were deferred: a crash between archiving and logging it) is cut
        off; that is only left after a log of format 1 records, since `durability.restore_scene` gives
        a format 2 log every frame the archive holds. Any other difference (a log repaired by hand, an archive that began after the session's
        first frames) leaves an archive that cannot serve corrections, and so does a frame that cannot be
        archived now (a disk still full): the log holds it, and the next restart archives it."""
        logged = logged or {}
        try:
            while len(self.entries) < frames and len(self.entries) in logged:
                payload = logged[len(self.entries)]
                self.append_frame(wire.unpack(payload).get("frame_id"), payload_digest(payload), payload)
        except OSError as exc:  # a disk still full: the scene is served from the log, corrections wait
            self.problem = self.problem or archive_failure(exc)
            return
        if len(self.entries) == frames + 1 and self._records and self._records[-1][1]:
            self.cut()
        if len(self.entries) != frames:
            self.problem = (f"{ARCHIVE}: holds {len(self.entries)} of the session's {frames} frames; "
                            "corrections are refused")

    def close(self) -> None:
        """Archive the deferred frames, stop the writer, close the files."""
        if self._writer is not None:
            self._queue.put(None)
            self._writer.join()
            self._writer = None
        self._log.close()
        with self._reading:
            if self._fd >= 0:
                os.close(self._fd)
                self._fd = -1
