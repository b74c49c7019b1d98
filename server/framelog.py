"""The frame log of one session: append-only, CRC-checked, fsynced before a frame is acknowledged.

A record (format 2) is ``magic | u32 payload length | u64 index | u32 CRC-32 of the payload |
u32 CRC-32 of the 20 header bytes before it | payload`` (little-endian). Two kinds:

- a frame record (magic ``CGF2``): ``index`` is the frame's arrival index and the payload its msgpack
  message, as `server.wire.frame_from_message` reads it;
- a checkpoint (magic ``CGK2``): written as the first record of a fresh log right after a snapshot;
  ``index`` is the number of frames the snapshot holds, and the payload (msgpack) the session's
  frame-id table, so that a retried frame is recognised after a restart too. A log that starts with a
  checkpoint for N > 0 frames and finds no snapshot holding them says loudly that frames are missing.

Logs written before format 2 hold format 1 records (magics ``CGF1``, ``CGK1``: ``magic | u32 length |
u64 index | u32 CRC-32 of (length, index, payload) | payload``). They are read by their own rules, and
a log of them goes on with format 2 records: every record names its format by its magic.

Damage is told apart from a crash. A crash mid-append can only leave a *torn tail*: a prefix of one
record after the last intact one, whose header is incomplete, or complete and intact (its CRC holds)
with its payload running past the end of the file. That record was never acknowledged (the
acknowledgement follows the fsync), so it is cut off. Anything else (a header that fails its CRC, a
record that fails its CRC while its bytes are all there, intact records after a bad one) is *damage*:
acknowledged frames may sit in it, so nothing is cut; the session is not served until it is restored
from its frame archive (`server.durability`) or an operator repairs it (`repaired`). Format 1 has no
CRC of its own header, so there a length made longer by damage reads as a torn tail.

A torn tail is torn only as far as the log can tell: a file that lost the end of its last acknowledged
record (truncated) holds the same bytes. The frame archive, written only after a frame's record is
fsynced, tells them apart where it holds the frame (`server.durability.restore_scene`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Literal

FRAME_MAGIC, CHECKPOINT_MAGIC = b"CGF2", b"CGK2"
# magic, payload length, index, a CRC: format 1's header (its CRC over length, index and payload), and
# format 2's first 20 bytes (its CRC over the payload), which a CRC of these 20 bytes follows
FIELDS = struct.Struct("<4sIQI")
HEADER = struct.Struct("<4sIQII")
MAGICS = {FRAME_MAGIC: 2, CHECKPOINT_MAGIC: 2, b"CGF1": 1, b"CGK1": 1}  # magic -> format
CHECKPOINT_MAGICS = (CHECKPOINT_MAGIC, b"CGK1")
NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # EFBIG: a file-size limit (ulimit -f), space as well


class StorageError(OSError):
    """A write that the service could not make durable; nothing of it was applied.

    ``full`` is true when the cause is a full disk or quota (the client may retry later)."""

    def __init__(self, what: str, exc: OSError):
        super().__init__(exc.errno, f"{what}: {exc.strerror or exc}")
        self.full = exc.errno in NO_SPACE


class LogWedged(StorageError):
    """A failed append whose partial record could not be cut off: the log's tail is unknown."""

    def __init__(self, message: str):
        OSError.__init__(self, errno.EIO, message)
        self.full = False


class Fenced(StorageError):
    """A write by an owner whose lease (``FrameLog.lease``, see `server.cluster.lease`) another owner
    has taken since: refused, nothing written."""

    def __init__(self, message: str):
        OSError.__init__(self, errno.ESTALE, message)
        self.full = False


@dataclass(frozen=True)
class Record:
    offset: int
    index: int  # frame index; for a checkpoint, the frames its snapshot holds
    payload: memoryview  # of the scanned bytes: scanning a file (mapped) copies none of its payloads
    checkpoint: bool
    version: int = 2  # its format

    @property
    def start(self) -> int:
        """The offset of its payload."""
        return self.offset + (HEADER if self.version == 2 else FIELDS).size

    @property
    def end(self) -> int:
        return self.start + len(self.payload)


@dataclass(frozen=True)
class Scan:
    """What a log holds: its intact records up to the first problem, and what that problem is."""

    records: list[Record]  # the intact prefix
    end: int  # offset just past the intact prefix
    size: int  # file size
    torn: bool  # bytes after ``end`` are a torn tail (as far as the log can tell, never acknowledged)
    later: list[Record]  # intact records found after damage (empty when torn or clean)
    version: int = 2  # the format of its last record (the torn one, if any): the rules its tail is read by

    @property
    def damaged(self) -> bool:
        return self.end < self.size and not self.torn

    def describe(self) -> str:
        after = f"; {len(self.later)} intact records follow it" if self.later else ""
        return f"damaged record at byte {self.end} of {self.size}{after}"


def _crc_v1(length: int, index: int, payload: bytes) -> int:
    return zlib.crc32(payload, zlib.crc32(struct.pack("<IQ", length, index)))


def encode(index: int, payload: bytes, checkpoint: bool = False) -> bytes:
    """A format 2 record."""
    fields = FIELDS.pack(CHECKPOINT_MAGIC if checkpoint else FRAME_MAGIC, len(payload), index, zlib.crc32(payload))
    return fields + struct.pack("<I", zlib.crc32(fields)) + payload


RECORD, SHORT, BAD = "record", "short", "bad"


def _parse(data: bytes, pos: int) -> tuple[str, Record | None]:
    """What starts at ``pos`` (before the end of ``data``): an intact record (RECORD, it), the prefix of
    one that runs to the end of ``data`` (SHORT: what a crash mid-append leaves), or neither (BAD)."""
    magic = bytes(data[pos:pos + 4])
    version = MAGICS.get(magic)
    if version is None:
        return (SHORT if len(magic) < 4 and any(m.startswith(magic) for m in MAGICS) else BAD), None
    header = (HEADER if version == 2 else FIELDS).size
    if len(data) - pos < header:
        return SHORT, None
    _, length, index, crc = FIELDS.unpack_from(data, pos)
    if version == 2 and zlib.crc32(data[pos:pos + FIELDS.size]) != int.from_bytes(data[pos + FIELDS.size:pos + header], "little"):
        return BAD, None  # a damaged header: its length cannot be trusted, so it is never a torn tail
    end = pos + header + length
    if end > len(data):
        return SHORT, None
    payload = memoryview(data)[pos + header:end]
    if (zlib.crc32(payload) if version == 2 else _crc_v1(length, index, payload)) != crc:
        return BAD, None
    return RECORD, Record(pos, index, payload, magic in CHECKPOINT_MAGICS, version)


def _record_at(data: bytes, pos: int) -> Record | None:
    """The intact record starting at ``pos``, or None."""
    return _parse(data, pos)[1] if pos < len(data) else None


def _next_record(data: bytes, start: int) -> Record | None:
    """The first intact record starting at or after ``start``."""
    while True:
        hits = [p for p in (data.find(m, start) for m in MAGICS) if p >= 0]
        if not hits:
            return None
        pos = min(hits)
        record = _record_at(data, pos)
        if record is not None:
            return record
        start = pos + 1


def scan(data: bytes) -> Scan:
    records, pos = [], 0
    while (record := _record_at(data, pos)) is not None:
        records.append(record)
        pos = record.end
    later: list[Record] = []
    if pos < len(data):
        record = _next_record(data, pos + 1)
        while record is not None:
            later.append(record)
            record = _record_at(data, record.end) or _next_record(data, record.end + 1)
    torn = pos < len(data) and not later and _parse(data, pos)[0] == SHORT
    version = MAGICS.get(bytes(data[pos:pos + 4])) or (records[-1].version if records else 2)
    return Scan(records, pos, len(data), torn, later, version)


def torn_at(data: bytes, pos: int) -> bool:
    """Whether the bytes of ``data`` from ``pos`` on are the prefix of one record (what a crash
    mid-append leaves), or none."""
    return pos >= len(data) or _parse(data, pos)[0] == SHORT


class FrameLog:
    """An open log, written by one writer (the session's lock) through an unbuffered O_APPEND descriptor,
    so that a failed write leaves no bytes behind in a buffer to be flushed later."""

    def __init__(self, path: Path):
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        # set where several processes may own the session (`server.cluster.lease.Lease`): every append
        # and reset then runs inside ``lease.held()``, which raises `Fenced` once another owner took it
        self.lease = None

    def append(self, index: int, payload: bytes, checkpoint: bool = False) -> int:
        """Append one frame record (or a checkpoint) and fsync it; returns its offset. On failure the
        partial record is cut off at once and `StorageError` raised; if even that fails, `LogWedged`
        (the file's tail is unknown until a restart reads it again). With a `lease`, `Fenced` when
        another owner took the session: nothing is written."""
        with self.fenced():
            offset = os.fstat(self._fd).st_size
            data = encode(index, payload, checkpoint)
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(self._fd, view):]
                os.fsync(self._fd)
            except OSError as exc:
                try:
                    self.truncate(offset)
                except OSError as again:
                    raise LogWedged(f"{self.path}: cannot cut a failed append back ({again.strerror or again})") from exc
                raise StorageError(f"{self.path.name}: cannot append a record", exc) from exc  # a frame, checkpoint or correction
            return offset

    def fenced(self) -> contextlib.AbstractContextManager:
        """The lease's check, held over a write; nothing to check without a lease."""
        return self.lease.held() if self.lease is not None else contextlib.nullcontext()

    def truncate(self, offset: int) -> None:
        with self.fenced():
            os.ftruncate(self._fd, offset)
            os.fsync(self._fd)

    def size(self) -> int:
        return os.fstat(self._fd).st_size

    def reset(self, records: list[bytes]) -> None:
        """Replace the whole log by ``records`` (encoded), atomically: a crash leaves the old or the new."""
        with self.fenced():
            write_atomic(self.path, b"".join(records))
            os.close(self._fd)
            self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, data: bytes | Callable[[BinaryIO], object]) -> None:
    """Write temp, fsync, rename, fsync the folder; on failure the temp file is removed and the old
    file is left as it was. ``data``: the bytes, or a function that writes them to the open file."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data) if isinstance(data, (bytes, bytearray, memoryview)) else data(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except Exception:  # noqa: BLE001 - re-raised: a writer function may fail otherwise than on the disk
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    fsync_dir(path.parent)


RepairAction = Literal["truncate", "skip"]


def repaired(data: bytes, action: RepairAction, snapshot_frames: int, checkpoint: bytes | None) -> tuple[list[bytes], int, int]:
    """A damaged log's records after a repair: (encoded records, frames kept, intact frames dropped).

    ``truncate`` keeps the intact frame records before the damage, ``skip`` every intact frame record.
    Records the snapshot already holds (index below ``snapshot_frames``) go; the rest are numbered
    again from ``snapshot_frames`` so that they replay in order, after a fresh checkpoint (payload
    ``checkpoint``) when the snapshot holds frames."""
    found = scan(data)
    kept = [r for r in found.records if not r.checkpoint]
    lost = [r for r in found.later if not r.checkpoint]
    if action == "skip":
        kept, lost = kept + lost, []
    kept = [r for r in kept if r.index >= snapshot_frames]
    out = [encode(snapshot_frames, checkpoint, checkpoint=True)] if snapshot_frames and checkpoint is not None else []
    out += [encode(snapshot_frames + k, r.payload) for k, r in enumerate(kept)]
    return out, len(kept), len(lost)
