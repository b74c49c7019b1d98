"""Retention: which idle sessions to remove, by an idle time to live and a disk budget. No HTTP here.

What it reads of each session is its folder (`folder_usage`): the bytes of every file under it, and
the newest modification time of the folder and of everything in it. Every acknowledged frame is
appended and fsynced to the session's log first, and a correction writes to its archive, so that
time is at least the session's last frame or correction (a snapshot or a restart's repair may make
it later, never earlier): ``last_active``. Nothing is kept in memory, so a restart forgets nothing.

The policy (`plan`) is a pure function of those figures, the data directory's total, ``now`` and the
settings. Its hard floor: a session active within `FLOOR_S` (24 hours) is never removed, whatever the
settings (a time to live of 1 s, a budget of 1 byte); nor is one that is busy (a request holds its
lock, or a correction re-folds in the background). Sessions whose files need an operator
(unavailable) count towards the disk but are never removed: damage is for a person to judge.

Removal goes through `SessionStore.delete` (one rename to a tombstone, then the files; the scene's
memory released), which takes the session's lock without waiting and looks again under it, so a
session that a frame or a correction reached after the plan was made is kept.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

from .session_errors import SessionNotFound

log = logging.getLogger("canonical.retention")

FLOOR_S = 24 * 3600.0  # a session active more recently than this is never removed


@dataclass(frozen=True)
class Usage:
    bytes: int  # of every file under the folder
    last_active: float  # unix time: the newest modification of the folder or of anything under it


@dataclass(frozen=True)
class Candidate:
    """What the policy reads of one session."""

    id: str
    last_active: float
    disk_bytes: int
    busy: bool = False


@dataclass(frozen=True)
class Removal:
    id: str
    reason: Literal["ttl", "disk_budget"]
    last_active: float
    disk_bytes: int


def folder_usage(path: Path) -> Usage:
    """Bytes and newest modification time under ``path`` (0 and 0.0 when it is gone). Files removed
    while it walks (a snapshot's commit, a delete) count as gone."""
    total, newest = 0, 0.0
    for root, dirs, files in os.walk(path):
        for name in (".", *dirs, *files):
            try:
                st = os.stat(os.path.join(root, name), follow_symlinks=False)
            except FileNotFoundError:
                continue
            newest = max(newest, st.st_mtime)
            if name in files:
                total += st.st_size
    return Usage(total, newest)


def plan(sessions: list[Candidate], used_bytes: int, now: float, ttl_s: float | None,
         budget_bytes: int | None) -> list[Removal]:
    """The sessions to remove, in order: first those idle longer than ``ttl_s``, then the oldest idle
    ones while the data directory's ``used_bytes`` exceed ``budget_bytes`` (None: no such limit).
    Busy sessions and those active within `FLOOR_S` of ``now`` are never chosen."""
    idle = sorted((s for s in sessions if not s.busy and now - s.last_active > FLOOR_S), key=lambda s: s.last_active)
    removals: list[Removal] = []
    for s in idle:
        if ttl_s is not None and now - s.last_active > ttl_s:
            reason = "ttl"
        elif budget_bytes is not None and used_bytes > budget_bytes:
            reason = "disk_budget"
        else:
            continue
        removals.append(Removal(s.id, reason, s.last_active, s.disk_bytes))
        used_bytes -= s.disk_bytes
    return removals


def candidate(session) -> Candidate:
    """A served session as the policy reads it (`server.session.Session`)."""
    usage = folder_usage(session.path)
    busy = session.lock.locked() or session.corrections.background is not None
    return Candidate(session.id, usage.last_active, usage.bytes, busy)


def prune(store, ttl_s: float | None, budget_bytes: int | None, dry_run: bool = False, now: float | None = None) -> dict:
    """Apply the policy to a `server.store.SessionStore` now (with ``dry_run``, only say what would go).
    Returns the report that ``POST /v1/sessions/prune`` answers."""
    now = time.time() if now is None else now
    used = folder_usage(store.data_dir).bytes
    removals = plan([candidate(s) for s in store.list()], used, now, ttl_s, budget_bytes)
    removed = [r for r in removals if dry_run or _remove(store, r, now)]
    return {"dry_run": dry_run, "removed": [asdict(r) for r in removed], "data_dir_bytes": used,
            "freed_bytes": sum(r.disk_bytes for r in removed), "session_ttl_s": ttl_s,
            "disk_budget_bytes": budget_bytes, "floor_s": FLOOR_S}


def _remove(store, planned: Removal, now: float) -> bool:
    """Delete the planned session unless it is busy or was reached since the plan (looked at under its
    lock), or is gone already; returns whether this removed it."""
    def changed(session) -> bool:
        return session.corrections.background is not None or folder_usage(session.path).last_active > planned.last_active

    try:
        removed = store.delete(planned.id, keep_if=changed)
    except SessionNotFound:  # deleted meanwhile
        return False
    if removed:
        log.warning("session %s removed (%s): idle %.1f h, %d bytes", planned.id, planned.reason,
                    (now - planned.last_active) / 3600, planned.disk_bytes)
    return removed
