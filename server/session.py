"""A session: one scene, its frame log and its lock, and what a request does to them. No HTTP here.

A frame (`Session.add_frame`) is folded under the session's lock: a retry of a frame_id it folded
already gets its first report back; otherwise its record is appended to the frame log and fsynced on
a writer thread (`LOG_WRITERS`) while the frame folds, and the acknowledgement waits for both. A fold
whose record is not durable is undone, a record whose fold fails is cut off again. The folded frame
then goes to the frame archive (`server.archive`), and a due snapshot starts (`server.snapshots`).
The session's files and their restore: `server.durability`; its corrections: `server.corrections`.

Locks: ``Session.lock`` serialises what reads or writes one session's scene and files (fold,
snapshot, digest); rendering works on decoded Gaussians outside it, so a render never sees a
half-folded scene and never blocks another session. Decoded Gaussians come from `Scene.gaussians`,
which decodes once per change and holds the scene's own lock only to copy its sums, so folds go on
while a decode runs. Renders show the last colour solution; the solve itself (`Session.solve_colours`)
runs in the background, also outside the session's lock (`server.solves`).
"""

from __future__ import annotations

import logging
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import InitVar, dataclass, field
from pathlib import Path
from typing import Callable, ClassVar

from canonical_core import Frame, Gaussians, SceneConfig
from canonical_core.decode import SolveStopped
from canonical_core.scene import FoldReport, PreparedFrame, Scene
from canonical_core.scene.folding import fold_cost
from canonical_core.scene.mesh import Mesh, scene_mesh
from canonical_core.scene.scene import DEFAULT_UNDO_DEPTH
from canonical_core.scene.undo import MAX_UNDO_SHARE

from .archive import SessionArchive
from .digests import names_payload, payload_digest
from .corrections import BACKGROUND_FRAMES, Corrections
from .durability import checkpoint_payload, restore_scene, write_chosen
from .frame_ids import FoldedFrame, FrameIds
from .framelog import FrameLog, LogWedged, StorageError
from .memory import MemoryBudget
from .ordering import FrameOrder
from .retention import folder_usage
from .session_errors import FrameIdConflict, FrameOutOfOrder, MemoryBudgetBusy, SessionNotFound, SessionUnavailable
from .snapshots import Snapshots
from .track import append_camera

log = logging.getLogger("canonical.store")  # the store's logger: one name for all that the store holds

# the frame log's appends (digest, write, fsync) run here while their frames fold: one writer per job
# that can fold at a time is enough (a session's appends are ordered by its lock)
LOG_WRITERS = ThreadPoolExecutor(max_workers=8, thread_name_prefix="frame-log")
UNDO_DEPTH = DEFAULT_UNDO_DEPTH  # folds an archived session's scene can roll back in place (`Scene.rollback`)
# frames prepared ahead of their fold (`Session.prepare`) held at once, all sessions together: each
# holds what its fold would make anyway (its evidence, about 130 bytes a pixel), and more than the
# ingest workers make while the folds run would save no fold time
PREPARED_AHEAD = threading.BoundedSemaphore(2)
# the most a prepared frame may hold while it waits (a 640x480 frame holds at most about 40 MB): a
# larger frame does that work in its fold, so that waiting frames hold at most twice this; frames of
# more pixels than PREPARED_MAX_PIXELS (about a megapixel: 130 bytes a pixel, label channels more)
# are not prepared at all, so as not to make what would then be dropped
PREPARED_MAX_BYTES = 128 * 2**20
PREPARED_MAX_PIXELS = 1280 * 720


class Ahead:
    """A frame prepared ahead of its fold (`Scene.prepare`), holding one of `PREPARED_AHEAD`'s slots
    until `release`, or until it is dropped unreleased (a request cancelled while it was prepared)."""

    def __init__(self, frame: PreparedFrame):
        self.frame: PreparedFrame | None = frame
        self._slot = weakref.finalize(self, PREPARED_AHEAD.release)  # runs once: here or when collected

    def release(self) -> None:
        self.frame = None
        self._slot()


@dataclass(eq=False)
class Session:
    """One session: its scene, frame log and frame-id table (what answers a retry), and the lock that
    serialises them. Its snapshots (`Snapshots`) and corrections (`Corrections`) work on it."""

    id: str
    path: Path
    config: SceneConfig
    created: float
    scene: Scene
    log: FrameLog
    snapshot_frames: InitVar[int]  # the frames its snapshot holds (kept by `snapshots`)
    frame_ids: dict[str, FoldedFrame] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    deleted: bool = False
    wedged: str | None = None  # why the log cannot take appends until a restart (its tail is unknown)
    archive: SessionArchive | None = None  # the kept frames (None: retention "none")
    version: int = 0  # bumped by every fold and correction: a correction computed on an older one is refused
    corrected: int = 0  # corrections that changed the served scene (its open event streams tell their pages)
    recoloured: int = 0  # colour solves kept for the served scene (its open pages redraw: `fold_events`)
    background_frames: int = BACKGROUND_FRAMES  # re-folds longer than this run in the background
    undo_depth: int = field(default_factory=lambda: UNDO_DEPTH)  # folds its scene can roll back in place
    preallocate_voxels: int = 0  # voxels whose memory its scenes commit up front (`Scene.preallocate`)
    budget: MemoryBudget | None = None  # the service's memory, which each fold reserves its worst case from
    colour_solves_stopped: int = 0  # background colour solves that gave way to a frame of it
    order: FrameOrder = field(init=False, repr=False)  # the turns of its numbered frames (`server.ordering`)
    chosen: dict[str, str] = field(default_factory=dict)  # why meta.json's settings are what they are (`Scene.chosen`)
    snapshots: Snapshots = field(init=False, repr=False)  # its snapshot, and the one being written
    corrections: Corrections = field(init=False, repr=False)  # its corrections, and the one re-folding
    snapshots_class: ClassVar[type[Snapshots]] = Snapshots  # what makes `snapshots` (`server.cluster` fences them)
    _counts: tuple[int, int] = field(init=False, repr=False)  # (frames, voxels) as last read under the lock

    def __post_init__(self, snapshot_frames: int):
        self.frame_ids = FrameIds(self.frame_ids)
        self.order = FrameOrder()
        self.snapshots = self.snapshots_class(self, snapshot_frames)
        self.corrections = Corrections(self)
        self._prepare_scene()

    def _prepare_scene(self) -> None:
        """The served scene's settings that its snapshot does not keep. Sessions that can be
        corrected keep undo records of their last folds: a correction of recent frames then rolls the
        served scene back and re-folds only them (`Corrections.correct`). And the scene commits the
        memory of `preallocate_voxels` voxels up front."""
        if self.archive is not None:
            self.scene.keep_undo(self.undo_depth, MAX_UNDO_SHARE)
        self._counts = (self.scene.frames, len(self.scene))
        self.preallocate(self.scene)
        self._keep_chosen()

    def _keep_chosen(self) -> None:
        """meta.json records the settings the scene chose from its first frame (`Scene.chosen`), once,
        so a restart folds with them whatever a later version would choose. A failed write is logged
        and tried again after the next fold; meanwhile a restart finds them in the snapshot, or
        chooses them again from the same first frame."""
        if self.scene.config == self.config:
            return
        try:
            write_chosen(self.path, self.scene.config, self.scene.chosen)
        except OSError as exc:
            log.warning("session %s: cannot record its chosen settings in meta.json (%s)", self.id, exc)
            return
        self.config, self.chosen = self.scene.config, dict(self.scene.chosen)

    def preallocate(self, scene: Scene) -> None:
        """`Scene.preallocate` of `preallocate_voxels` voxels, at most the session's ``max_voxels``."""
        scene.preallocate(min(self.preallocate_voxels, self.config.max_voxels or self.preallocate_voxels))

    def prepare(self, frame: Frame) -> Ahead | None:
        """``frame``'s fold begun now, on the caller's thread without the session's lock, while the
        frames before it fold (`Scene.prepare`); None where nothing was made, the frame has more than
        `PREPARED_MAX_PIXELS`, no slot of `PREPARED_AHEAD` is free, or what was made is over
        `PREPARED_MAX_BYTES` (dropped: the fold makes it again). Give it to `add_frame`, and
        `Ahead.release` it after."""
        if frame.width * frame.height > PREPARED_MAX_PIXELS or not PREPARED_AHEAD.acquire(blocking=False):
            return None
        try:
            prepared = self.scene.prepare(frame)
        except BaseException:
            PREPARED_AHEAD.release()
            raise
        if prepared.config is None or prepared.nbytes() > PREPARED_MAX_BYTES:
            PREPARED_AHEAD.release()
            return None
        return Ahead(prepared)

    # -- writing (callers hold no lock; these take it) ------------------------------------------
    def add_frame(self, payload: bytes, frame: Frame, snapshot_every_frames: int, snapshot_every_seconds: float,
                  index: int | None = None, prepared: PreparedFrame | None = None) -> tuple[FoldReport, bool]:
        """Log (fsynced), fold, maybe snapshot; returns the fold report and whether it is a replay.

        A frame whose ``frame_id`` the session already folded is not folded again: its first report
        comes back (replay = True), or `FrameIdConflict` if its content differs. The record is logged
        on a writer thread while the frame folds, and the report is returned once both are done. A
        frame that cannot be made durable raises `StorageError`, its fold undone. On a ValueError the
        log record is cut off again and the scene is unchanged (the library validates before it mutates).

        A numbered frame (``index``: its place in the stream, its turn awaited with `order`) is folded
        only in that place, else `FrameOutOfOrder`; its refusal refuses the frames waiting behind it.
        ``prepared``: the frame's `prepare`d fold, folded in its place (the same bits)."""
        with self.lock:
            self.check_alive()
            try:
                result = self._add_frame(payload, frame, snapshot_every_frames, snapshot_every_seconds, index, prepared)
            except (FrameOutOfOrder, MemoryBudgetBusy):  # not refused: its turn stays, and the client sends it again
                raise
            except Exception as exc:
                self.order.refused(index, exc)
                raise
            self.order.folded(self.scene.frames)
            self._counts = (self.scene.frames, len(self.scene))
            return result

    def _add_frame(self, payload: bytes, frame: Frame, snapshot_every_frames: int, snapshot_every_seconds: float,
                   index: int | None, prepared: PreparedFrame | None) -> tuple[FoldReport, bool]:
        """`add_frame` once it is the frame's turn, under the lock."""
        known = self.frame_ids.get(frame.frame_id) if frame.frame_id is not None else None
        if known is not None:
            if not names_payload(known.digest, payload):
                raise FrameIdConflict(f"frame_id: {frame.frame_id!r} was folded as frame {known.index} with other content")
            report = known.report or {"frame_index": known.index, "observations": 0, "new_voxels": 0,
                                      "updated_voxels": 0, "representative_switches": 0, "ms": 0.0}
            append_camera(self.path, known.index, frame.camera)  # its row, had a crash come before it
            return FoldReport(**report), True
        if index is not None:
            self.order.check_turn(index, self.scene.frames)
        if self.wedged:
            raise SessionUnavailable(self.id, self.wedged, retry_later=True)
        refolding = self.archive is not None and self.corrections.background is not None
        if refolding:  # the re-fold catches up on the archive: it must take this frame at once
            self.archive.check_at_once()
        frames = self.scene.frames
        with self.budget.reserve(fold_cost(self.scene, frame)) if self.budget is not None else nullcontext():
            logged = LOG_WRITERS.submit(lambda: (payload_digest(payload), self.log.append(frames, payload)))
            try:
                report = self.scene.fold(frame if prepared is None or prepared.frame is not frame else prepared)
            except Exception as exc:
                self._fold_failed(logged, exc)
                raise
        try:
            digest, offset = logged.result()
        except StorageError as exc:
            self._append_failed(exc, frames)
            raise
        if self.archive is not None:
            try:
                self.archive.keep_folded(frame.frame_id, digest, payload, at_once=refolding)
            except StorageError:  # not in the scene the correction swaps in: taken back, not acknowledged
                try:
                    self.log.truncate(offset)
                except OSError as exc:  # its record stays in the log: no more frames until a restart reads it
                    self.wedged = f"frames.log: a refused frame's record could not be cut off ({exc.strerror or exc})"
                finally:
                    self._recover(frames, "a fold whose frame was not archived")
                raise
        append_camera(self.path, report.frame_index, frame.camera)
        if frame.frame_id is not None:
            self.frame_ids[frame.frame_id] = FoldedFrame(report.frame_index, digest, report.to_dict())
        self.version += 1
        self._keep_chosen()
        self.snapshots.after_fold(snapshot_every_frames, snapshot_every_seconds)
        return report, False

    def _fold_failed(self, logged, exc: Exception) -> None:
        """A fold raised while its record was being logged: the record is cut off again once written.
        A ValueError left the scene unchanged (the library validates before it mutates); anything else
        may have left it half-folded, so it is rebuilt from disk (without this frame)."""
        try:
            _, offset = logged.result()
        except StorageError as storage:
            self._note_wedged(storage)
        else:
            self.log.truncate(offset)
        if not isinstance(exc, ValueError):
            self._recover(None, "a failed fold")

    def _append_failed(self, exc: StorageError, frames: int) -> None:
        """The frame folded but its record is not durable (cut off, the log wedged, or the session
        fenced by another owner): the fold is undone."""
        self._note_wedged(exc)
        self._recover(frames, "a fold whose frame was not logged")

    def _recover(self, frames: int | None, after: str) -> None:
        """The scene back to its first ``frames`` frames by its undo records where they reach back
        (None: not by them), else rebuilt from disk; a session that cannot be is no longer served."""
        try:
            if frames is not None and self.scene.undo_floor <= frames:
                self.scene.rollback(frames)
            else:
                self._reload()
        except Exception:
            log.exception("session %s: cannot be rebuilt after %s; no longer serving it", self.id, after)
            self.deleted = True

    def _note_wedged(self, exc: StorageError) -> None:
        if isinstance(exc, LogWedged):
            self.wedged = f"{exc.strerror}; restart the service once the storage is fixed"
            log.error("session %s: %s", self.id, self.wedged)

    def _reload(self) -> None:
        self.snapshots.cancel()
        self.log.close()
        self.scene, self.log, self.snapshots.frames, frame_ids = restore_scene(self.path, self.config, chosen=self.chosen)
        self.frame_ids = FrameIds(frame_ids)
        self._prepare_scene()

    def snapshot(self, background: bool = False) -> None:
        """Snapshot the session if it has frames its snapshot lacks: now, or with ``background`` off the
        caller's path (`Snapshots.soon`)."""
        with self.lock:
            if not self.deleted and self.scene.frames != self.snapshots.frames:
                self.snapshots.soon() if background else self.snapshots.take()

    def checkpoint(self) -> bytes:
        """The payload of the log's checkpoint for the served scene: its frame-id table and the archived
        corrections it holds."""
        return checkpoint_payload(self.frame_ids, self.corrections.held())

    def check_alive(self) -> None:
        if self.deleted:
            raise SessionNotFound(self.id)

    # -- reading --------------------------------------------------------------------------------

    def counts(self) -> tuple[int, int]:
        """(frames, voxels) as a reader that does not wait may show them: read now when the session's
        lock is free, else as last read under it. A fold or a correction holds the lock, and a
        correction of recent frames rolls the scene back before it folds them again: a state no one
        was answered with, which the session list, the viewer and the track must not show."""
        if self.lock.acquire(blocking=False):
            try:
                self._counts = (self.scene.frames, len(self.scene))
            finally:
                self.lock.release()
        return self._counts
    def gaussians(self, max_gaussians: int | None = None, features: bool = True) -> tuple[Gaussians, int]:
        """Decoded Gaussians (`Scene.gaussians`: decoded once per change, in the last colour solution,
        never waiting for a solve; without ``features``, F_scene may be left out) and their label_dim."""
        with self.lock:
            self.check_alive()
            scene = self.scene
        g = scene.gaussians(max_gaussians, colours="last", features=features)
        return g, 0 if g.labels is None else int(g.labels.shape[1])

    def colour_solve_due(self) -> bool:
        """Whether the served scene's colours are solved for an earlier state than its own
        (`Scene.colour_solve_due`); False for a deleted session."""
        return not self.deleted and self.scene.colour_solve_due()

    def solve_colours(self, stop: Callable[[], bool] | None = None) -> bool:
        """`Scene.solve_colours` of the served scene, outside the session's lock: folds go on
        meanwhile. ``stop`` can end it between its steps (counted in ``colour_solves_stopped``).
        Returns whether a solution was kept."""
        with self.lock:
            self.check_alive()
            scene = self.scene
        try:
            solved = scene.solve_colours(stop)
        except SolveStopped:
            self.colour_solves_stopped += 1
            return False
        self.recoloured += solved
        return solved

    def mesh(self, min_support: float = 0.0) -> Mesh:
        """The scene's surface mesh (`scene_mesh`: its sums copied under the scene's own lock, so folds
        go on while it is meshed)."""
        with self.lock:
            self.check_alive()
            scene = self.scene
        return scene_mesh(scene, min_support)

    @property
    def retention(self) -> str:
        return self.archive.retention if self.archive is not None else "none"

    def summary(self) -> dict:
        """What the session list shows of it: cheap (no decode, no lock), so listing many sessions is.
        Its files are read without the lock: one that a snapshot commit or a delete removes meanwhile
        counts as gone."""
        usage = folder_usage(self.path)
        frames, voxels = self.counts()
        return {"id": self.id, "frames": frames, "voxels": voxels, "created": self.created,
                "last_active": usage.last_active or self.created,
                "voxel_size": self.scene.config.voxel_size, "memory_bytes": self.scene.memory_bytes(),
                "disk_bytes": usage.bytes, "archive_retention": self.retention,
                "state": "read_only" if self.wedged else "ok", "problem": self.wedged}

    def stats(self) -> dict:
        gaussians = len(self.gaussians(features=False)[0])  # a decode if none is cached, outside the scene's lock
        with self.lock:
            self.check_alive()
            self._counts = (self.scene.frames, len(self.scene))  # the summary's, read under the lock held here
            stats = self.scene.stats()
            archive = self.archive
            return {
                "archive_retention": self.retention,
                "archive_bytes": archive.nbytes() if archive is not None else 0,
                "archive_frames": sum(e.kept for e in archive.entries) if archive is not None else 0,
                "archive_problem": archive.problem if archive is not None else None,
                **self.summary(),
                "gaussians": gaussians,
                "undo_bytes": self.scene.undo_bytes(),
                "label_dim": stats["label_dim"],
                "inconsistent_depth_below": stats["inconsistent_depth_below"],
                "sensor": stats["sensor"],
                "chosen": stats["chosen"],
                "snapshot_frames": self.snapshots.frames,
                "snapshot_error": self.snapshots.error,
                "colours_solved_frames": self.scene.colours_solved_frames(),
                "colour_solves_stopped": self.colour_solves_stopped,
                "config": self.scene.config.to_dict(),
            }

    def digest(self) -> dict:
        """The library's digest of the fused state: equal iff the sessions fused the same frames."""
        with self.lock:
            self.check_alive()
            return {"id": self.id, "frames": self.scene.frames, "voxels": len(self.scene), "sha256": self.scene.digest()}
