"""A session's files, and how they are read back: restore, quarantine (`server.repair` repairs them). No locks here: a session is
restored before it is served, and repaired while no server runs on its directory.

- ``frames.log``: the append-only frame log (`server.framelog`). A frame is appended and fsynced before it is
  acknowledged; the append runs on a writer thread while the frame folds (the fsync is a wait on the disk, the
  fold is compute), and the acknowledgement waits for both. An append that fails (a full disk) is cut off at
  once and the fold is undone (the scene rolled back, or rebuilt from disk); a record whose fold fails is cut
  off again. A render in that moment may show a frame that is not yet acknowledged; it never loses one that
  is. On start a torn tail (a crash mid-append: never acknowledged) is cut off; damage anywhere else is never
  cut. The frame archive is the log's second copy: it takes a frame only once its log record is fsynced, so
  every frame it holds was acknowledged, and a log that lacks one of them (damaged, or cut short: a cut into
  the last record looks like a torn tail to the log alone) gets them back from it. Otherwise the log is copied
  to ``quarantine/`` and the session is not served until ``canonical repair`` decides.
- ``scene.snap``: `Scene.to_bytes` snapshot (atomic), holding ``scene.frames`` frames. Due every
  ``snapshot_every_frames`` frames or ``snapshot_every_seconds``, and written on shutdown; after it the log is
  replaced by one checkpoint record (the frames the snapshot holds and the frame-id table) and the records of
  the frames after them. A due snapshot is written off the acknowledged path (`server.snapshots`); a crash
  before it is committed leaves the previous snapshot and the whole log (its ``scene.snap.<n>.next`` file is
  removed on start). Restart = load snapshot, replay records whose index >= the snapshot's frame count.
  Folding is deterministic, so the replayed scene equals the uninterrupted one bit for bit. A snapshot that
  cannot be written is not an error of the request that triggered it: that frame is already durable in the
  log; the failure shows in the session's stats and in /metrics.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from pathlib import Path
from typing import NamedTuple

import msgpack

from canonical_core import SceneConfig
from canonical_core.scene import Scene
from canonical_core.scene.corrections import corrected_stream
from canonical_core.scene.choices import filled_from
from canonical_core.scene.snapshot import read_config

from . import wire
from .archive import ARCHIVE, Retention, SessionArchive
from .digests import payload_digest
from .frame_ids import FoldedFrame
from .framelog import FrameLog, Scan, encode, scan, torn_at, write_atomic
from .payloads import DamagedFrame
from .session_errors import SnapshotLost, Unrestorable
from .track import append_camera, tracked, write_track

log = logging.getLogger("canonical.store")  # the store's logger: one name for all that the store holds

LOG, SNAPSHOT, QUARANTINE, META = "frames.log", "scene.snap", "quarantine", "meta.json"
PENDING_SNAPSHOT = "scene.snap.{}.next"  # a snapshot written off the acknowledged path, not yet committed


class Restored(NamedTuple):
    scene: Scene
    log: FrameLog
    snapshot_frames: int
    frame_ids: dict[str, FoldedFrame]


def remove_quietly(path: Path) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


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


def write_chosen(path: Path, config: SceneConfig, chosen: dict[str, str]) -> None:
    """meta.json with the settings its scene chose from the first frame (``config``) and why (``chosen``)."""
    meta = json.loads((path / META).read_text())
    meta |= {"config": config.to_dict(), "config_sha256": config_digest(config.to_dict()), "chosen": chosen}
    write_atomic(path / META, json.dumps(meta, indent=1).encode())


def session_meta(path: Path) -> tuple[dict, SceneConfig]:
    """A session's meta.json and its settings, checked against the session's own record of them: the
    snapshot's settings where there is a snapshot, else the digest meta.json got at creation (sessions
    of earlier versions have none: theirs are taken as they are). The log folds again only with the
    settings it was folded with, so a difference (meta.json edited by hand) raises `Unrestorable`
    naming meta.json and the setting; nothing is changed."""
    restore = f"restore {META} from a backup (the session's other files are kept as they are)"
    try:  # garbled by hand or by a disk: a file to put back, not a fault of the service's
        meta = json.loads((path / META).read_text())
    except ValueError as exc:
        raise Unrestorable(f"{META}: not valid JSON ({exc}); {restore}") from None
    missing = [key for key in ("id", "created", "config") if not isinstance(meta, dict) or key not in meta]
    if missing:
        raise Unrestorable(f"{META}: lacks {', '.join(missing)}; {restore}")
    try:
        config = SceneConfig.from_dict(meta["config"])
    except (ValueError, TypeError) as exc:
        raise Unrestorable(f"{META}: config: {exc}; {restore}") from None
    if (path / SNAPSHOT).exists():
        try:
            held = read_config(path / SNAPSHOT)
        except ValueError:  # an unreadable snapshot: the restore says so
            return meta, config
        if filled_from(config, held).to_dict() != held.to_dict():  # settings chosen by the first frame agree
            name, given, made = _first_difference(filled_from(config, held).to_dict(), held.to_dict())
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


def restore_session(path: Path, config: SceneConfig, retention: Retention,
                    chosen: dict | None = None) -> tuple[Restored, SessionArchive | None]:
    """`restore_scene` (``chosen`` as it takes it) with the session's archive. An archived correction the
    snapshot lacks (a crash before the files caught up) re-folds the archive, snapshotted, and remakes
    the camera track: a restart gives the corrected scene, never a mixture. So does a snapshot lost (gone,
    unreadable) where the archive, with the log's frames it lacks, holds every frame: the snapshot is
    moved to ``quarantine/`` and made again from the frames."""
    archive = SessionArchive(path / ARCHIVE, retention) if retention != "none" else None
    if archive is None or archive.problem or archive.corrections <= _corrections_of(path):
        try:
            restored = restore_scene(path, config, archive, chosen)
        except SnapshotLost as lost:
            if _holds_every_frame(path, archive):
                return _refolded(path, config, retention, chosen, archive, lost)
            if archive is not None:
                archive.close()
            raise
        except BaseException:
            if archive is not None:
                archive.close()
            raise
        if archive is not None and archive.problem is None:
            archive.cut_to(restored.scene.frames, logged_frames(path))
        return restored, archive
    return _refolded(path, config, retention, chosen, archive)


def _holds_every_frame(path: Path, archive: SessionArchive | None) -> bool:
    """Whether ``archive`` holds, once the log's frames it lacks are added, every frame the session
    acknowledged (retention "keyframes" keeps some only): then the scene can be folded from it alone."""
    if archive is None or archive.problem is not None:
        return False
    found = scan((path / LOG).read_bytes() if (path / LOG).is_file() else b"")
    frames = max([r.index + (not r.checkpoint) for r in found.records], default=0)
    archive.cut_to(max(frames, len(archive.entries)), logged_frames(path))
    return archive.problem is None and not found.damaged and all(e.kept for e in archive.entries)


def _refolded(path: Path, config: SceneConfig, retention: Retention, chosen: dict | None, archive: SessionArchive,
              lost: SnapshotLost | None = None) -> tuple[Restored, SessionArchive]:
    """The session's scene folded again from its archive, snapshotted, with its log restarted and its
    camera track made again (`restore_session`): for a correction the snapshot lacks, or where the
    snapshot was ``lost`` (then it is kept under ``quarantine/``, not cut away, and folded from zero)."""
    snap = path / SNAPSHOT
    if lost is not None and snap.exists():
        quarantine(path, snap.read_bytes(), SNAPSHOT)
        snap.unlink()
    scene = Scene.load(snap) if snap.exists() else Scene(config)
    entries = list(archive.entries)
    dropped = {k for k, e in enumerate(entries) if not e.kept}
    cameras: list = []  # the re-folded frames' track (the file may predate the correction)
    try:
        scene.adopt(Scene.refolded(scene.config, corrected_stream(tracked(archive.frames(entries), cameras), {}, dropped),
                                   scene.appearance))
    except ValueError as exc:  # a background correction that cannot be made (the voxel cap): undone, as its job does
        if archive.background_correction is None:
            raise
        archive.append_undo(archive.background_correction, f"{type(exc).__name__}: {exc}")
        archive.close()
        return restore_session(path, config, retention, chosen)
    write_track(path, cameras)
    if dropped:
        archive.append_correction({}, [entries[k].arrival for k in dropped], min(dropped))
    frame_ids = archived_frame_ids(archive, {})
    write_atomic(snap, scene.to_bytes())
    write_atomic(path / LOG, encode(scene.frames, checkpoint_payload(frame_ids, archive.corrections), checkpoint=True))
    why = "a correction the snapshot did not hold" if lost is None else f"the snapshot lost: {lost}"
    log.warning("%s: re-folded %d frames from the archive (%s)", path, scene.frames, why)
    return Restored(scene, FrameLog(path / LOG), scene.frames, frame_ids), archive


def logged_frames(path: Path) -> dict[int, bytes]:
    """The frame log's frames: stream position -> wire payload (what a restart archives when the
    archive had not caught up with them)."""
    data = (path / LOG).read_bytes() if (path / LOG).is_file() else b""
    return {r.index: r.payload for r in scan(data).records if not r.checkpoint}


def _frame_ids_of(checkpoint: bytes) -> dict[str, FoldedFrame]:
    table = msgpack.unpackb(checkpoint)["frame_ids"]
    return {k: FoldedFrame(index, digest, report) for k, (index, digest, report) in table.items()}


def quarantine(path: Path, data: bytes, name: str = LOG) -> Path:
    """A copy of a damaged log (or of what a repair cut from the archive) under ``quarantine/``, one per
    distinct content, so nothing is lost."""
    folder = path / QUARANTINE
    folder.mkdir(exist_ok=True)
    target = folder / f"{name}.{hashlib.blake2b(data, digest_size=8).hexdigest()}"
    if not target.exists():
        write_atomic(target, data)
    return target


def _quarantined(path: Path, data: bytes) -> str:
    try:
        return f"copied to {quarantine(path, data)}"
    except OSError as exc:
        return f"could not be copied aside ({exc.strerror or exc}); it is left as it is"


def _acknowledged(found: Scan, archive: SessionArchive | None) -> int:
    """The stream's first frames known to be acknowledged by the archive: it takes a frame only once its
    log record is fsynced. Not the last one after a format 1 record: archives written before frames were
    deferred took a frame before its record (`SessionArchive.cut_to` cuts that one)."""
    if archive is None:
        return 0
    return max(0, len(archive.entries) - (found.version == 1))


def _frames(first: int, end: int) -> str:
    return f"frame {first} was" if end - first == 1 else f"frames {first}..{end - 1} were"


def _from_archive(data: bytes, found: Scan, archive: SessionArchive | None, held: int, acknowledged: int) -> bytes | str:
    """The log's bytes with what follows its intact records rebuilt: the frames from ``held`` (what the
    snapshot and those records hold) to ``acknowledged`` taken from the archive, then the log's own
    intact records after those. Or why that cannot be done without losing a frame ("" where the archive
    holds no frame that the log lacks)."""
    if archive is None or acknowledged <= held:
        return ""
    if not found.records and held:
        return "its first record, the checkpoint of the snapshot's frames (their frame ids), is lost"
    later = [r for r in found.later if r.checkpoint or r.index >= acknowledged]
    if [(r.checkpoint, r.index) for r in later] != [(False, k) for k in range(acknowledged, acknowledged + len(later))]:
        return f"the log's intact records after the damage do not follow on from the frames {ARCHIVE} holds"
    records = []
    try:
        for k, payload in enumerate(archive.payloads(archive.entries[held:acknowledged]), held):
            if payload is None:
                return f"{ARCHIVE} does not keep frame {k}'s content (archive retention {archive.retention!r})"
            records.append(encode(k, payload))
    except DamagedFrame as exc:
        return f"{exc} (frame {held + len(records)})"
    # past the last record known intact, the bytes may hold no more than the frames restored after it (and
    # a torn append): more may be a frame acknowledged but not archived yet
    last = found.later[-1] if found.later else None
    past = records[max(0, last.index + 1 - held):] if last else records
    if not torn_at(data, (last.end if last else found.end) + sum(map(len, past))):
        return f"the damaged bytes hold more than the frames that {ARCHIVE} holds"
    return data[:found.end] + b"".join(records) + b"".join(data[r.offset:r.end] for r in later)


def _restore_from_archive(path: Path, data: bytes, found: Scan, archive: SessionArchive | None, held: int,
                          acknowledged: int) -> bytes:
    """The log, damaged or lacking acknowledged frames, rebuilt by `_from_archive` (its old bytes copied
    to ``quarantine/`` first); returns its new bytes. Raises `Unrestorable` where it cannot be rebuilt
    without losing a frame."""
    rebuilt = _from_archive(data, found, archive, held, acknowledged)
    what = found.describe() if found.damaged else f"it ends {'inside' if found.torn else 'before'} frame {held}'s record"
    if acknowledged > held:
        what += f"; {_frames(held, acknowledged)} acknowledged ({ARCHIVE} holds {'it' if acknowledged - held == 1 else 'them'})"
    if isinstance(rebuilt, str):
        raise Unrestorable(f"{LOG}: {what}{'; ' + rebuilt if rebuilt else ''}; the log {_quarantined(path, data)}. "
                           "`canonical repair --action truncate` keeps the frames before the damage, `--action skip` "
                           f"every intact frame (and either drops those of {ARCHIVE} that the log then lacks)")
    where = quarantine(path, data)
    write_atomic(path / LOG, rebuilt)
    log.error("%s: %s: %s; restored from %s (the log as it was is %s)", path, LOG, what, ARCHIVE, where)
    return rebuilt


def restore_scene(path: Path, config: SceneConfig, archive: SessionArchive | None = None,
                  chosen: dict | None = None) -> Restored:
    """Load the snapshot (if any) and replay the log after it, the scene saying why its settings are
    what they are as meta.json records it (``chosen``, `Scene.chosen`): the replayed frames' reports
    are then those of their first folds (but for the fold time). With the session's frame ``archive``, the
    acknowledged frames that the log lacks or holds damaged are restored from it first
    (`_restore_from_archive`). Raises `Unrestorable` when the files do not add up: a damaged log, or one
    that lacks acknowledged frames, that the archive cannot make whole (quarantined first), a missing
    log, a snapshot missing or older than the log says."""
    for stale in path.glob(PENDING_SNAPSHOT.format("*") + "*"):  # written off the acknowledged path, never committed
        remove_quietly(stale)
    if not (path / LOG).is_file():
        raise Unrestorable(f"{LOG} is missing: frames after the last snapshot may be lost "
                           "(`canonical repair` starts an empty log)")
    snap = path / SNAPSHOT
    try:
        scene = Scene.load(snap) if snap.exists() else Scene(config)
    except ValueError as exc:
        raise SnapshotLost(f"{SNAPSHOT}: {exc}; restore it from a backup") from None
    if chosen and scene.config == config:  # settings chosen from the first frame, and kept in meta.json
        scene.chosen = dict(chosen)
    data = (path / LOG).read_bytes()
    found = scan(data)
    acknowledged = _acknowledged(found, archive)
    held = max([scene.frames] + [r.index + (not r.checkpoint) for r in found.records])
    if found.damaged or held < acknowledged:
        found = scan(_restore_from_archive(path, data, found, archive, held, acknowledged))
    snapshot_frames = scene.frames
    checkpoints = [r for r in found.records if r.checkpoint]
    records = [r for r in found.records if not r.checkpoint]
    first = checkpoints[-1].index if checkpoints else (records[0].index if records else 0)
    if first > scene.frames:
        what = "missing" if not snap.exists() else f"older than the log (it holds {scene.frames} frames)"
        raise SnapshotLost(f"{SNAPSHOT} is {what}: the log continues from frame {first}, so frames "
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
            frame = wire.frame_from_message(msg)
            # a record the snapshot holds already (a crash between snapshot and log restart) only adds its id
            report = scene.fold(frame).to_dict() if record.index == scene.frames else None
        except ValueError as exc:
            if k != len(records) - 1 or record.index < acknowledged:
                # Records after it exist (or the archive holds it), so this one was folded and acknowledged
                # once: never drop it (e.g. a library that validates more strictly now). The session is not served.
                frame_log.close()
                raise Unrestorable(f"{LOG}: acknowledged frame {record.index} no longer folds: {exc}") from exc
            # the last record's fold failed: it was never acknowledged (the crash came before its truncation)
            log.warning("%s: dropping the unacknowledged last log record (frame %d): %s", path, record.index, exc)
            frame_log.truncate(record.offset)
            break
        append_camera(path, record.index, frame.camera)  # its row, had the crash come before the frame's answer
        if msg.get("frame_id") is not None:  # a frame the checkpoint names was rewritten by a correction: its digest stays
            known = frame_ids.get(msg["frame_id"])
            digest = known.digest if known is not None else payload_digest(record.payload)
            frame_ids[msg["frame_id"]] = FoldedFrame(record.index, digest, report)
    return Restored(scene, frame_log, snapshot_frames, frame_ids)


def restored_frames(path: Path, config: SceneConfig, retention: Retention) -> int:
    """The frames a start would serve of the session at ``path`` (`restore_session`, its files closed
    again); raises `Unrestorable` as it does."""
    restored, archive = restore_session(path, config, retention)
    restored.log.close()
    if archive is not None:
        archive.close()
    return restored.scene.frames
