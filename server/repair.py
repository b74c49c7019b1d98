"""``canonical repair``: an unrestorable session's files made to add up again, offline (no server runs on
the data directory), keeping every frame that can be kept; what was cut goes under ``quarantine/``."""

from __future__ import annotations

import os
import time
from pathlib import Path

from canonical_core.scene import Scene

from .archive import ARCHIVE, SessionArchive
from .durability import LOG, QUARANTINE, SNAPSHOT, quarantine
from .framelog import RepairAction, repaired, scan, write_atomic
from .session_errors import Unrestorable


def repair(path: Path, action: RepairAction) -> str:
    """Make an unrestorable session's files add up again, keeping every frame that can be kept (see
    `server.framelog.repaired`); the log as it was stays under ``quarantine/``, and the frame archive is
    made to match the log (`_archive_after_repair`). Returns what it did."""
    snap = path / SNAPSHOT
    try:
        snapshot_frames = Scene.load(snap).frames if snap.exists() else 0
    except ValueError as exc:
        raise Unrestorable(f"{SNAPSHOT}: {exc}; restore it from a backup (repair cannot rebuild it)") from None
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    if data:
        quarantine(path, data)
    found = scan(data)
    checkpoints = [r for r in found.records + found.later if r.checkpoint]
    records, kept, dropped = repaired(data, action, snapshot_frames, checkpoints[-1].payload if checkpoints else None)
    write_atomic(path / LOG, b"".join(records))
    # the frames kept, by their index before the repair: in order unless a skip left one out
    kept_frames = [r.index for r in found.records + (found.later if action == "skip" else [])
                   if not r.checkpoint and r.index >= snapshot_frames]
    archived = _archive_after_repair(path, kept_frames == list(range(snapshot_frames, snapshot_frames + kept)),
                                     snapshot_frames + kept)
    return (f"the snapshot's {snapshot_frames} frames and {kept} logged frames after them kept; {dropped} intact "
            f"frames after the damage dropped (the old log is under {QUARANTINE}/){archived}")


def _archive_after_repair(path: Path, in_order: bool, frames: int) -> str:
    """The frame archive made to match a repaired log of ``frames`` frames, so that a start does not take
    the frames it holds beyond them for frames the log lost: those are cut off (copied to ``quarantine/``
    first). Where the log's frames no longer follow the archive's (``in_order`` false: a repair skipped a
    frame) or they cannot be cut (a correction follows them), the archive is moved to ``quarantine/``
    whole: the session starts a new one, which cannot serve corrections of the frames before it."""
    if not (path / ARCHIVE).is_file():
        return ""
    archive = SessionArchive(path / ARCHIVE, "all")
    extra = len(archive.entries) - frames
    try:
        if in_order and extra <= 0:
            return ""
        if in_order:
            archive.cut(extra, aside=lambda data: quarantine(path, data, ARCHIVE))
            return f"; the {extra} frames of {ARCHIVE} after them dropped (copied to {QUARANTINE}/)"
    except ValueError:
        pass
    finally:
        archive.close()
    (path / QUARANTINE).mkdir(exist_ok=True)
    target = path / QUARANTINE / f"{ARCHIVE}.{int(time.time())}"
    os.replace(path / ARCHIVE, target)
    return f"; {ARCHIVE} no longer matches the log: moved to {target} (corrections need a new archive)"
