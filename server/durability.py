"""A session's files, and how they are read back: restore, repair, quarantine. No locks here: a
session is restored before it is served, and repaired while no server runs on its directory.

- ``frames.log``: the append-only frame log (`server.framelog`). A frame is appended and fsynced
  before it is acknowledged; the append runs on a writer thread while the frame folds (the fsync is
  a wait on the disk, the fold is compute), and the acknowledgement waits for both. An append that
  fails (a full disk) is cut off at once and the fold is undone (the scene rolled back, or rebuilt
  from disk); a record whose fold fails is cut off again. A render in that moment may show a frame
  that is not yet acknowledged; it never loses one that is. On start a torn tail (a crash
  mid-append: never acknowledged) is cut off; damage anywhere else is never cut: the log is copied to
  ``quarantine/`` and the session is not served until ``canonical repair`` decides.
- ``scene.snap``: `Scene.to_bytes` snapshot (atomic), holding ``scene.frames`` frames. Due every
  ``snapshot_every_frames`` frames or ``snapshot_every_seconds``, and written on shutdown; after it
  the log is replaced by one checkpoint record (the frames the snapshot holds and the frame-id
  table) and the records of the frames after them. A due snapshot is written off the acknowledged
  path (`server.snapshots`); a crash before it is committed leaves the previous snapshot and the
  whole log (its ``scene.snap.<n>.next`` file is removed on start).
  Restart = load snapshot, replay records whose index >= the snapshot's frame count. Folding is
  deterministic, so the replayed scene equals the uninterrupted one bit for bit. A snapshot that
  cannot be written is not an error of the request that triggered it: that frame is already durable
  in the log; the failure shows in the session's stats and in /metrics.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import msgpack

from canonical_core import SceneConfig
from canonical_core.scene import Scene
from canonical_core.scene.corrections import corrected_stream
from canonical_core.scene.snapshot import read_config

from . import wire
from .archive import ARCHIVE, Retention, SessionArchive, payload_digest
from .framelog import FrameLog, RepairAction, encode, repaired, scan, write_atomic
from .session_errors import Unrestorable

log = logging.getLogger("canonical.store")  # the store's logger: one name for all that the store holds

LOG, SNAPSHOT, QUARANTINE, META = "frames.log", "scene.snap", "quarantine", "meta.json"
PENDING_SNAPSHOT = "scene.snap.{}.next"  # a snapshot written off the acknowledged path, not yet committed


@dataclass(frozen=True)
class FoldedFrame:
    """What the session remembers of a frame that carried a frame_id: enough to answer its retry."""

    index: int
    digest: str  # of its log record's payload
    # the fold report it got; None where a crash between a snapshot and the log's restart left only
    # the frame's record (its report is then not known: the retry gets zero counts)
    report: dict | None


class Restored(NamedTuple):
    scene: Scene
    log: FrameLog
    snapshot_frames: int
    frame_ids: dict[str, FoldedFrame]


def remove_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def checkpoint_payload(frame_ids: dict[str, FoldedFrame], corrections: int = 0) -> bytes:
    """The checkpoint's payload: the frame-id table and how many archived corrections the snapshot holds."""
    return msgpack.packb({"frame_ids": {k: [v.index, v.digest, v.report] for k, v in frame_ids.items()},
                          "corrections": corrections})


def _corrections_of(path: Path) -> int:
    """How many archived corrections the snapshot holds, by the log's last checkpoint (0 without one)."""
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    checkpoints = [r for r in scan(data).records if r.checkpoint]
    return int(msgpack.unpackb(checkpoints[-1].payload).get("corrections", 0)) if checkpoints else 0


def archived_frame_ids(archive: SessionArchive, known: dict[str, FoldedFrame]) -> dict[str, FoldedFrame]:
    """The frame-id table after a correction: the archive's frames with their new positions; a
    removed frame's id is forgotten (sending it again folds it again). Reports keep their counts."""
    out = {}
    for position, e in enumerate(archive.entries):
        if e.frame_id is not None:
            report = (known.get(e.frame_id) or FoldedFrame(0, "", None)).report
            out[e.frame_id] = FoldedFrame(position, e.digest, report and {**report, "frame_index": position})
    return out


def config_digest(config: dict) -> str:
    """The digest of a session's settings as its meta.json holds them (``config_sha256``, written at
    creation): of the mapping as written, so a later version's reading of it does not change it."""
    return hashlib.sha256(json.dumps(config, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def session_meta(path: Path) -> tuple[dict, SceneConfig]:
    """A session's meta.json and its settings, checked against the session's own record of them: the
    snapshot's settings where there is a snapshot, else the digest meta.json got at creation (sessions
    of earlier versions have none: theirs are taken as they are). The log folds again only with the
    settings it was folded with, so a difference (meta.json edited by hand) raises `Unrestorable`
    naming meta.json and the setting; nothing is changed."""
    meta = json.loads((path / META).read_text())
    config = SceneConfig.from_dict(meta["config"])
    restore = f"restore {META} from a backup (the session's other files are kept as they are)"
    if (path / SNAPSHOT).exists():
        try:
            held = read_config(path / SNAPSHOT)
        except ValueError:  # an unreadable snapshot: the restore says so
            return meta, config
        if held.to_dict() != config.to_dict():
            name, given, made = _first_difference(config.to_dict(), held.to_dict())
            raise Unrestorable(f"{META}: config.{name} is {given!r}, but {SNAPSHOT} was made with {made!r}: the "
                               f"session folds only with the settings it was made with; {restore}")
    elif "config_sha256" in meta and meta["config_sha256"] != config_digest(meta["config"]):
        raise Unrestorable(f"{META}: config was changed after the session was created (it no longer matches its "
                           f"config_sha256): the session folds only with the settings it was made with; {restore}")
    return meta, config


def _first_difference(given: dict, made: dict, prefix: str = "") -> tuple[str, object, object]:
    """(dotted name, value in ``given``, value in ``made``) of the first setting the two mappings differ in."""
    for name in given:
        if isinstance(given[name], dict) and isinstance(made.get(name), dict) and given[name] != made[name]:
            return _first_difference(given[name], made[name], f"{prefix}{name}.")
        if given[name] != made.get(name):
            return f"{prefix}{name}", given[name], made.get(name)
    raise ValueError("the settings do not differ")


def restore_session(path: Path, config: SceneConfig, retention: Retention) -> tuple[Restored, SessionArchive | None]:
    """`restore_scene`, with the session's frame archive. When the archive holds a correction that the
    snapshot does not (a crash between archiving a correction and snapshotting its scene), the scene is
    re-folded from the archive and snapshotted, so a restart gives the corrected scene, never a mixture."""
    archive = SessionArchive(path / ARCHIVE, retention) if retention != "none" else None
    if archive is None or archive.problem or archive.corrections <= _corrections_of(path):
        restored = restore_scene(path, config)
        if archive is not None and archive.problem is None:
            archive.cut_to(restored.scene.frames, logged_frames(path))
        return restored, archive
    snap = path / SNAPSHOT
    scene = Scene.load(snap) if snap.exists() else Scene(config)
    entries = list(archive.entries)
    dropped = {k for k, e in enumerate(entries) if not e.kept}
    scene.adopt(Scene.refolded(config, corrected_stream(archive.frames(entries), {}, dropped), scene.appearance))
    if dropped:
        archive.append_correction({}, [entries[k].arrival for k in dropped], min(dropped))
    frame_ids = archived_frame_ids(archive, {})
    write_atomic(snap, scene.to_bytes())
    write_atomic(path / LOG, encode(scene.frames, checkpoint_payload(frame_ids, archive.corrections), checkpoint=True))
    log.warning("%s: re-folded %d frames from the archive (a correction the snapshot did not hold)", path, scene.frames)
    return Restored(scene, FrameLog(path / LOG), scene.frames, frame_ids), archive


def logged_frames(path: Path) -> dict[int, bytes]:
    """The frame log's frames: stream position -> wire payload (what a restart archives when the
    archive had not caught up with them)."""
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    return {r.index: r.payload for r in scan(data).records if not r.checkpoint}


def _frame_ids_of(checkpoint: bytes) -> dict[str, FoldedFrame]:
    table = msgpack.unpackb(checkpoint)["frame_ids"]
    return {k: FoldedFrame(index, digest, report) for k, (index, digest, report) in table.items()}


def quarantine(path: Path, data: bytes) -> Path:
    """A copy of a damaged log under ``quarantine/`` (one per distinct content), so nothing is lost."""
    folder = path / QUARANTINE
    folder.mkdir(exist_ok=True)
    target = folder / f"{LOG}.{hashlib.blake2b(data, digest_size=8).hexdigest()}"
    if not target.exists():
        write_atomic(target, data)
    return target


def restore_scene(path: Path, config: SceneConfig) -> Restored:
    """Load the snapshot (if any) and replay the log after it. Raises `Unrestorable` when the files do
    not add up: a damaged log (quarantined first), a missing log, a snapshot missing or older than the
    log says."""
    for stale in path.glob(PENDING_SNAPSHOT.format("*") + "*"):  # written off the acknowledged path, never committed
        remove_quietly(stale)
    if not (path / LOG).is_file():
        raise Unrestorable(f"{LOG} is missing: frames after the last snapshot may be lost "
                           "(`canonical repair` starts an empty log)")
    data = (path / LOG).read_bytes()
    found = scan(data)
    if found.damaged:
        try:
            where = f"copied to {quarantine(path, data)}"
        except OSError as exc:
            where = f"could not be copied aside ({exc.strerror or exc}); it is left as it is"
        raise Unrestorable(f"{LOG}: {found.describe()}; the log {where}. `canonical repair --action truncate` "
                           "keeps the frames before the damage, `--action skip` every intact frame")
    snap = path / SNAPSHOT
    try:
        scene = Scene.load(snap) if snap.exists() else Scene(config)
    except ValueError as exc:
        raise Unrestorable(f"{SNAPSHOT}: {exc}; restore it from a backup") from None
    snapshot_frames = scene.frames
    checkpoints = [r for r in found.records if r.checkpoint]
    records = [r for r in found.records if not r.checkpoint]
    first = checkpoints[-1].index if checkpoints else (records[0].index if records else 0)
    if first > scene.frames:
        what = "missing" if not snap.exists() else f"older than the log (it holds {scene.frames} frames)"
        raise Unrestorable(f"{SNAPSHOT} is {what}: the log continues from frame {first}, so frames "
                           f"{scene.frames}..{first - 1} are not on disk. Restore {SNAPSHOT} from a backup, or "
                           "`canonical repair` keeps the log's frames without them")
    frame_log = FrameLog(path / LOG)
    if found.torn:
        log.warning("%s: cutting off a torn log tail (%d bytes at offset %d, never acknowledged)", path,
                    found.size - found.end, found.end)
        frame_log.truncate(found.end)
    frame_ids = _frame_ids_of(checkpoints[-1].payload) if checkpoints else {}
    for k, record in enumerate(records):
        try:
            if record.index > scene.frames:
                raise ValueError(f"log: record for frame {record.index} follows frame {scene.frames - 1}")
            msg = wire.unpack(record.payload)
            # a record the snapshot holds already (a crash between snapshot and log restart) only adds its id
            report = scene.fold(wire.frame_from_message(msg)).to_dict() if record.index == scene.frames else None
        except ValueError as exc:
            if k != len(records) - 1:
                # Records after it exist, so this one was folded and acknowledged once: never drop it
                # (e.g. a library that validates more strictly now). The session is not served.
                frame_log.close()
                raise Unrestorable(f"{LOG}: acknowledged frame {record.index} no longer folds: {exc}") from exc
            # the last record's fold failed: it was never acknowledged (the crash came before its truncation)
            log.warning("%s: dropping the unacknowledged last log record (frame %d): %s", path, record.index, exc)
            frame_log.truncate(record.offset)
            break
        if msg.get("frame_id") is not None:  # a frame the checkpoint names was rewritten by a correction: its digest stays
            known = frame_ids.get(msg["frame_id"])
            digest = known.digest if known is not None else payload_digest(record.payload)
            frame_ids[msg["frame_id"]] = FoldedFrame(record.index, digest, report)
    return Restored(scene, frame_log, snapshot_frames, frame_ids)


def repair(path: Path, action: RepairAction) -> str:
    """Make an unrestorable session's files add up again, keeping every frame that can be kept (see
    `server.framelog.repaired`); the log as it was stays under ``quarantine/``. Returns what it did."""
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
    return (f"the snapshot's {snapshot_frames} frames and {kept} logged frames after them kept; {dropped} intact "
            f"frames after the damage dropped (the old log is under {QUARANTINE}/)")
