"""A session's corrections: new poses for archived frames and frames removed, re-folded in the request
or in the background, and the session's files brought up to date after one.

Files: ``base.snap`` and ``base.json`` hold a corrected stream's state at a frame count before its end
(`BASE`), so that the next correction of recent frames starts from it instead of from the stream's
first frame. The corrections themselves are records of the frame archive (`server.archive`).
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
from dataclasses import dataclass
from pathlib import Path

from canonical_core.scene import Scene
from canonical_core.scene.corrections import FieldError, check_poses, corrected_stream, resolve_frames
from canonical_core.scene.undo import MAX_UNDO_SHARE

from . import wire
from .archive import ArchiveClosed, SessionArchive
from .durability import LOG, SNAPSHOT, archived_frame_ids
from .frame_ids import FrameIds
from .framelog import scan, write_atomic
from .session_errors import CorrectionRefused, SessionUnavailable
from .track import correct_track

log = logging.getLogger("canonical.store")  # the store's logger: one name for all that the store holds

BASE, BASE_META = "base.snap", "base.json"  # a corrected stream's state at a frame count before its end
BASE_EVERY = 25  # a correction keeps the state at the last multiple of this below its frame count
BACKGROUND_FRAMES = 64  # default: a correction that would re-fold more frames re-folds in the background


@dataclass
class CorrectionJob:
    """A correction re-folding in the background (`Corrections.correct`), as its status reports it."""

    id: str
    total: int  # frames to re-fold (grows with the frames that arrive meanwhile)
    state: str = "pending"  # pending, running, done, failed
    refolded: int = 0
    error: str | None = None
    result: dict | None = None

    def status(self) -> dict:
        return {"correction_id": self.id, "state": self.state, "refolded": self.refolded, "total": self.total,
                "error": self.error, "result": self.result}


def counted(frames, job: CorrectionJob):
    """``frames``, counting each one in ``job.refolded`` as the re-fold takes the next."""
    for frame in frames:
        yield frame
        job.refolded += 1


class LatestStates(dict):
    """Frame count -> state bytes, holding the two latest only: the states a re-fold passes cost a
    whole scene each, and a correction keeps one, from before the scene's end."""

    def __setitem__(self, frames: int, state: bytes) -> None:
        super().__setitem__(frames, state)
        while len(self) > 2:
            del self[min(self)]


class Corrections:
    """The corrections of one session (`server.session.Session`). They work on the session's
    ``scene`` (replaced by the corrected one), ``frame_ids`` and ``version``, its ``archive``, ``log``
    and snapshots (``snapshots``), under its ``lock``; a failure that leaves the files behind the
    archive sets its ``wedged``."""

    def __init__(self, session):
        self.session = session
        self.background: CorrectionJob | None = None  # the correction re-folding in the background, if one is
        self.jobs: dict[str, CorrectionJob] = {}  # background corrections since the start

    def held(self) -> int:
        """Archived corrections the served scene holds (not one still re-folding in the background)."""
        if self.session.archive is None:
            return 0
        return self.session.archive.corrections - (self.background is not None)

    def correct(self, poses: dict | None = None, remove: list | None = None, wait: bool = True) -> dict:
        """Give archived frames new poses (``{frame key: c2w}``) and/or remove frames (keys as in
        `corrections.resolve_frames`), as one durable step; returns what it did.

        The corrected scene is the re-fold of the archived frames, in order, with the corrections
        applied (`Scene.refolded`): equal to a session that was streamed the corrected frames.

        A correction whose frames are among the scene's last folds (``undo_depth``) rolls the served
        scene back and re-folds them under the session's lock (`Scene.rollback`): about k folds for
        the k most recent frames. Any other is computed outside the lock from the latest saved state
        before its first frame, so the old scene is served meanwhile; a fold or another correction
        that lands in the meantime makes it `CorrectionRefused` (409), nothing changed.

        The correction is archived (fsynced) before the scene is swapped and acknowledged. Then the
        files catch up: where the correction leaves the snapshot's frames as they were, the log is
        rewritten with the corrected frames after them; otherwise the scene is snapshotted and the
        log restarted. A restart between the two re-folds from the archive (`restore_session`). Bad
        keys or poses raise ValueError naming ``poses.<key>`` or ``frames.<key>``, nothing changed.

        A correction that would re-fold more than ``background_frames`` frames, or any with ``wait``
        False, is archived and answered at once (``state`` "pending", a ``correction_id``, and its
        ``status`` as accepted), and re-folds in the background (`_refold_in_background`); the old
        scene is served and takes frames meanwhile. Another correction that arrives then is
        `CorrectionRefused` (409)."""
        session = self.session
        with session.lock:
            session.check_alive()
            archive = self._usable_archive()
            if session.wedged:
                raise SessionUnavailable(session.id, session.wedged, retry_later=True)
            self._check_no_background()
            session.snapshots.cancel()  # the correction rewrites the files: a snapshot of before must not land after
            refs, entries, version = archive.refs(), list(archive.entries), session.version
            changed = check_poses(poses, refs) if poses else {}
            for key, k in zip(poses or {}, resolve_frames(list(poses or {}), refs, "poses")):  # "keyframes" keeps some
                if not entries[k].kept:
                    raise FieldError(f"poses.{key}", "the archive does not keep this frame (archive_retention "
                                                     "keyframes), so no correction can fold it again")
            removed = set(resolve_frames(remove or [], refs, "frames"))
            if not changed and not removed:
                raise ValueError("poses: names no frame")
            dropped = {k for k, e in enumerate(entries) if not e.kept} - removed  # retention "keyframes"
            first = min(set(changed) | removed | dropped)
            done = {"id": session.id, "corrected": len(set(changed) - removed), "removed": len(removed),
                    "dropped": len(dropped), "frames_before": session.scene.frames, "state": "done",
                    "correction_id": None}
            short = len(entries) - first <= session.background_frames
            if wait and short and first >= session.scene.undo_floor and all(e.kept for e in entries[first:]):
                self._correct_in_place(archive, entries, changed, removed | dropped, first)
                return {**done, "frames": session.scene.frames}
            bases = self._bases(archive, first)
            appearance = session.scene.appearance
            start = bases[0][0] if bases else 0
            # retention "keyframes" re-folds in the request: a frame it does not keep cannot be caught up on
            if archive.retention == "all" and (not wait or len(entries) - start > session.background_frames):
                job = CorrectionJob(secrets.token_hex(8), len(entries) - len(removed | dropped) - start)
                self._commit(archive, entries, changed, removed | dropped, first, job.id,
                             {k: done[k] for k in ("corrected", "removed", "dropped", "frames_before")})
                self.background = self.jobs[job.id] = job
                answer = {**done, "frames": session.scene.frames, "state": job.state, "correction_id": job.id,
                          "status": job.status()}  # the 202 answer: accepted, its re-fold not begun
                threading.Thread(target=self._refold_in_background, name=f"correction-{job.id}", daemon=True,
                                 args=(job, archive, bases, appearance, done, changed, removed | dropped)).start()
                return answer
        try:
            scene, checkpoints = self._refolded(archive, entries, changed, removed | dropped, appearance, bases)
        except ArchiveClosed:
            session.check_alive()  # deleted while it re-folded: 404
            raise
        with session.lock:
            session.check_alive()
            if session.version != version:
                raise CorrectionRefused("session_id", "a frame or another correction reached the session while this "
                                                      "correction was computed; send it again")
            self._commit(archive, entries, changed, removed | dropped, first)
            scene.carry_colour_solution(session.scene)
            session.scene = scene
            self._renumbered(done["frames_before"], changed, removed | dropped)
            self._persist()
            self._keep_base(checkpoints)
            return {**done, "frames": scene.frames}

    def _commit(self, archive: SessionArchive, entries: list, changed: dict, removed: set, first: int,
                job: str | None = None, summary: dict | None = None) -> None:
        """Archive the correction (fsynced: the commit point), and what follows from it in memory (for a
        background correction ``job``, at its swap; ``summary``: its answer's counts, for its status)."""
        archive.append_correction({entries[k].arrival: c2w for k, c2w in changed.items()},
                                  [entries[k].arrival for k in removed], first, job, summary)
        self.session.version += 1
        if job is None:
            self.session.frame_ids = FrameIds(archived_frame_ids(archive, self.session.frame_ids))

    def _check_no_background(self) -> None:
        job = self.background
        if job is not None:
            raise CorrectionRefused("session_id", f"correction {job.id} is still re-folding in the background "
                                                  f"({job.refolded} of {job.total} frames); send this one when its "
                                                  "status (GET .../corrections/{id}) says done")

    def _refold_in_background(self, job: CorrectionJob, archive: SessionArchive, bases: list[tuple[int, Path]],
                              appearance, done: dict, changed: dict, removed: set) -> None:
        """Re-fold the archived (corrected) stream from the latest valid saved state, then catch up on
        the frames that arrived meanwhile, in arrival order, and swap the scene in under the lock once
        none is left: the result equals the corrected stream folded afresh. A failure (the voxel cap,
        say) leaves the old scene served and the correction undone in the archive (`append_undo`):
        frames go on, and a restart neither retries nor counts it; where that cannot be written, the
        session is read-only until a restart, which retries it."""
        session = self.session
        job.state = "running"
        try:
            with session.lock:
                entries = list(archive.entries)
            scene, checkpoints = self._refolded(archive, entries, {}, set(), appearance, bases, job)
            while True:
                with session.lock:
                    session.check_alive()
                    arrived = archive.entries[len(entries):]
                    if not arrived:
                        self._swap_in(scene, checkpoints, archive, changed, removed)
                        job.result = {**done, "frames": scene.frames, "state": "done", "correction_id": job.id}
                        job.state, self.background = "done", None
                        return
                    job.total += len(arrived)
                for frame in archive.frames(arrived):
                    scene.fold(frame)
                    job.refolded += 1
                entries += arrived
        except Exception as exc:  # noqa: BLE001 - recorded in the status and the session's state
            if session.deleted or isinstance(exc, ArchiveClosed):
                # deleted (nothing left to correct), or the service stopping (the archive holds the
                # correction: the restart re-folds it): an end, not a failure of the re-fold
                why = "the session was deleted" if session.deleted else "the service stopped"
                job.state, job.error, self.background = "failed", f"stopped: {why}", None
                log.info("session %s: background correction %s stopped: %s", session.id, job.id, why)
                return
            log.exception("session %s: background correction %s failed", session.id, job.id)
            with session.lock:
                job.state, job.error, self.background = "failed", f"{type(exc).__name__}: {exc}", None
                try:  # the archive as the served scene again: frames go on, a restart neither retries nor counts it
                    archive.append_undo(job.id, job.error)
                except Exception as undo:  # noqa: BLE001 - the correction stays archived: read-only until a restart
                    session.wedged = (f"correction {job.id} failed while re-folding ({job.error}), and could not be "
                                      f"undone in the archive ({undo}); a restart retries it")

    def _swap_in(self, scene: Scene, checkpoints: dict[int, bytes], archive: SessionArchive, changed: dict,
                 removed: set) -> None:
        """The background re-fold's scene becomes the served one (the caller holds the lock)."""
        session = self.session
        scene.carry_colour_solution(session.scene)
        before = session.scene.frames
        session.scene, session.version = scene, session.version + 1
        self._renumbered(before, changed, removed)
        session.frame_ids = FrameIds(archived_frame_ids(archive, session.frame_ids))
        self.background = None
        self._persist()
        self._keep_base(checkpoints)

    def _renumbered(self, frames_before: int, changed: dict, removed: set) -> None:
        """What follows the served scene's change (under the lock): numbered frames in flight learn
        the new count (`FrameOrder.recounted`), the camera track takes the corrected poses and loses
        the removed frames (``changed``, ``removed``: stream positions before the correction; frames
        folded since into the old scene are renumbered with the rest), and the open event streams
        send a ``corrected`` event (`Session.corrected`)."""
        self.session.order.recounted(frames_before, self.session.scene.frames)
        correct_track(self.session.path, changed, removed)
        self.session.corrected += 1

    def status(self, correction_id: str) -> dict:
        """The status of a background correction; one this process did not start but the archive holds
        was finished by the restart that replayed it (its result: the counts it was answered with, and
        the frames the session holds now). Raises KeyError for an unknown id."""
        job = self.jobs.get(correction_id)
        if job is not None:
            return job.status()
        archive = self.session.archive
        held = None if archive is None else archive.status(correction_id, self.session.id, self.session.scene.frames)
        if held is None:
            raise KeyError(correction_id)
        return held

    def _correct_in_place(self, archive: SessionArchive, entries: list, changed: dict, removed: set,
                          first: int) -> None:
        """`correct` for frames among the last folds, under the session's lock: roll the scene back to
        ``first`` frames, fold the corrected frames after it, archive the correction, then what follows
        (`_renumbered`) and the files (the log or a snapshot). If a fold
        or the archive write fails, the scene is rolled back again and the old frames re-folded (they
        folded before), and the error is raised: nothing changed."""
        scene = self.session.scene
        frames_before = scene.frames

        def fold_from_first(frames) -> None:  # one step for renders and exports: never a half-corrected scene
            scene.refold_after(first, frames)

        tail = entries[first:]
        try:
            fold_from_first(corrected_stream(archive.frames(tail), {k - first: c2w for k, c2w in changed.items()},
                                             {k - first for k in removed}))
            self._commit(archive, entries, changed, removed, first)
        except BaseException:
            fold_from_first(list(archive.frames(tail)))
            raise
        self._renumbered(frames_before, changed, removed)  # before the files catch up (`server.track`)
        if first >= self.session.snapshots.frames:
            self._rewrite_log(archive, first)
        else:
            self._persist()

    def _rewrite_log(self, archive: SessionArchive, first: int) -> None:
        """After a correction whose first frame ``first`` comes after the snapshot's: the log's records
        from that frame on are cut off, the corrected frames appended, then a checkpoint counting the
        archive's corrections, so a restart (snapshot + log) gives the corrected scene without a new
        snapshot, and this costs the corrected frames' records only. Until that checkpoint is written
        the log counts fewer corrections than the archive, and a restart re-folds from the archive
        (`restore_session`). A failure makes the session read-only until a restart."""
        session = self.session
        found = scan(session.log.path.read_bytes())
        head = found.records[0].offset if found.records and found.records[0].checkpoint else -1  # the snapshot's
        after = [r for r in found.records if not r.checkpoint and r.index >= first and r.offset > head]
        try:
            session.log.truncate(after[0].offset if after else found.end)
            for k, msg in enumerate(archive.messages(archive.entries[first:])):
                session.log.append(first + k, wire.pack(msg))
            session.log.append(session.snapshots.frames, session.checkpoint(), checkpoint=True)
        except OSError as exc:
            session.wedged = (f"{LOG}: {exc.strerror or exc}; the correction is durable, restart the service to apply "
                              "it to the files")
            log.error("session %s: %s", session.id, session.wedged)

    def _bases(self, archive: SessionArchive, first: int) -> list[tuple[int, Path]]:
        """Saved states of the stream's first frames that a correction whose first touched frame is
        ``first`` may start from, latest first: the snapshot (it holds the stream's first
        ``snapshots.frames`` frames), and the state a correction kept (`BASE`) while no later
        correction touched a frame before it."""
        path = self.session.path
        bases = [(self.session.snapshots.frames, path / SNAPSHOT)]
        try:
            meta = json.loads((path / BASE_META).read_text())
            if all(f >= meta["frames"] for f in archive.firsts[meta["corrections"]:]):
                bases.append((int(meta["frames"]), path / BASE))
        except (OSError, ValueError, KeyError, TypeError):
            pass
        return sorted(((n, path) for n, path in bases if 0 < n <= first), reverse=True)

    def _refolded(self, archive: SessionArchive, entries: list, changed: dict, removed: set, appearance,
                  bases: list[tuple[int, Path]], job: CorrectionJob | None = None) -> tuple[Scene, dict[int, bytes]]:
        """The corrected stream folded, from the latest saved state of its unchanged first frames
        (`_bases`; exact: a snapshot round-trips the state bit for bit), so a correction of recent
        frames costs the folds since that state. Also returns the latest states it started from or
        passed at multiples of `BASE_EVERY` (frame count -> `Scene.to_bytes`). With ``job``, counts its
        progress."""
        session = self.session
        start, base, checkpoints = 0, None, LatestStates()
        for frames, path in bases:
            try:
                state = path.read_bytes()
                base = Scene.from_bytes(state)
            except (OSError, ValueError):
                continue
            if base.frames == frames:
                start, checkpoints[frames] = frames, state  # still a valid base after this correction
                break
            base = None
        stream = corrected_stream(archive.frames(entries[start:]), {k - start: c2w for k, c2w in changed.items()},
                                  {k - start for k in removed})
        if job is not None:
            job.total = len(entries) - len(removed) - start
            stream = counted(stream, job)
        # the settings the first frame chose stay, even where that frame is removed (`Scene.chosen`)
        config, chosen = session.scene.config, dict(session.scene.chosen)
        if base is None:
            base = Scene(config)
        base.keep_undo(session.undo_depth, MAX_UNDO_SHARE)  # the re-fold's last folds can be rolled back: a next correction of them is cheap
        session.preallocate(base)  # the re-fold and the scene it becomes grow into committed memory
        base.chosen = chosen
        return Scene.refolded(config, stream, appearance, base, BASE_EVERY, checkpoints), checkpoints

    def _keep_base(self, checkpoints: dict[int, bytes]) -> None:
        """Keep the latest state the re-fold started from or passed before the scene's end (`BASE`),
        for the next correction of recent frames (the snapshot is about to hold the whole scene).
        Written after the correction is durable; a failure only costs that next correction a longer
        re-fold."""
        session = self.session
        frames = max((n for n in checkpoints if n < session.scene.frames), default=0)
        if not frames:
            return
        try:
            write_atomic(session.path / BASE, checkpoints[frames])
            write_atomic(session.path / BASE_META, json.dumps({"frames": frames, "corrections": self.held()}).encode())
        except OSError as exc:
            log.warning("session %s: the re-fold's base state could not be kept (%s)", session.id, exc.strerror or exc)

    def _usable_archive(self) -> SessionArchive:
        archive = self.session.archive
        if archive is not None:
            archive.flush()  # corrections read every frame the scene holds
        if archive is None:
            raise CorrectionRefused("archive_retention", "this session keeps no frame archive (retention 'none'), "
                                                         "so its poses cannot be corrected nor frames removed")
        if archive.problem:
            raise CorrectionRefused("archive_retention", archive.problem)
        return archive

    def _persist(self) -> None:
        """Snapshot the corrected scene and restart the log with a checkpoint that counts the archive's
        corrections. A failure leaves the correction durable in the archive (a restart re-folds it), but
        the log cannot take frames on the old snapshot: the session is read-only until a restart."""
        session = self.session
        session.snapshots.take()
        if session.snapshots.error or session.snapshots.frames != session.scene.frames:
            session.wedged = (f"{session.snapshots.error}; the correction is durable, restart the service to apply it "
                              "to the files")
            log.error("session %s: %s", session.id, session.wedged)
