"""Agg, streaming: the scene that folds one frame at a time, a thin facade over its parts.

One frame's route through `Scene.fold` goes one way:

    depth front end (`depth_frontend`: denoise, hole completion, plane sweep, pending frames)
      -> evidence (`evidence.extract_evidence`)
      -> integration into the voxel map (`integrate.integrate`, `voxel_map.VoxelMap`)
      -> free space (`integrate.integrate_free_space`)

and `Scene.decode` / `Scene.gaussians` read the map through the decoder side (`decoding`).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import threading
import time
from concurrent.futures import Executor, Future
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from ..evidence import AppearanceUncertainty, DepthConsistency, extract_evidence, observation_sh_basis
from ..frame import Frame, depth_warnings
from ..gaussians import Gaussians
from ..decode.checkpoint import load_model as _load_model
from ..config import SceneConfig
from .corrections import FrameKey, FrameRef, check_poses, corrected_stream, resolve_frames
from .decoding import ColourSolution, DecodeInputs, SceneDecoding
from .depth_frontend import DepthFrontEnd
from .fields import fields_from_sums
from .free_space import SeeThroughHistory
from .integrate import Scratch, integrate, integrate_free_space
from .keyframes import Keyframes
from .undo import FoldUndo, UndoRing, history_slot, restore_history, restore_voxels
from .voxel_map import CapacityError, VoxelMap, gathered_sums

__all__ = ["CapacityError", "DecodeInputs", "FoldReport", "Scene"]

FORMAT_NAME = "canonicalgs-scene"
FORMAT_VERSION = 4  # 4 adds the per-view observation density (v3 files load with a density of 1)
# folds a scene that keeps its frames can roll back in place: each record holds the rows the fold
# touched and the whole see-through column, several times the fold's share of the state, so few
DEFAULT_UNDO_DEPTH = 4


@dataclass(frozen=True)
class FoldReport:
    """What one `Scene.fold` call did.

    ``frame_index`` is the frame's arrival index. A frame without depth and without a usable source
    view yet is ``pending``: accepted and kept, and folded (its depth estimated) by the call whose
    frame gives it a partner; that call counts it in ``also_folded``. ``denoised``: the frame's depth
    was far rougher than its noise model and was folded as its local median (`evidence.denoise`).
    ``warnings``: problems with the input that did not stop the fold, each ``"field: problem"``
    (e.g. depth that gave no observation). The ``description`` metadata reaches the HTTP schema.
    """

    frame_index: int = field(metadata={"description": "the frame's arrival index in the session"})
    observations: int = field(metadata={"description": "pixels folded"})
    new_voxels: int = field(metadata={"description": "voxels the frame created"})
    updated_voxels: int = field(metadata={"description": "existing voxels the frame touched"})
    representative_switches: int = field(metadata={"description": "voxels whose representative this frame replaced"})
    ms: float = field(metadata={"description": "the library's fold time, milliseconds"})
    pending: bool = field(default=False, metadata={"description": "a frame without depth waiting for a partner view (folded later)"})
    also_folded: int = field(default=0, metadata={"description": "earlier waiting frames this call folded"})
    completed_pixels: int = field(default=0, metadata={
        "description": "pixels whose missing depth the plane sweep filled (depth.completion)"})
    denoised: bool = field(default=False, metadata={
        "description": "the frame's depth was far rougher than its noise model and was replaced by a local median"})
    warnings: list[str] = field(default_factory=list, metadata={
        "description": "problems with the input that did not stop the fold, each 'field: problem'"})

    def to_dict(self) -> dict:
        return asdict(self)


class Scene:
    """A streaming CanonicalGS scene.

    Thread safety: `fold`, `decode_inputs`, `digest`, `to_bytes` and `gaussians` may be called from
    several threads; the scene's lock serialises what reads or writes its state, and decoding runs
    outside it (`gaussians`), so a fold never waits for a decode.

    With ``keep_frames=True`` the scene keeps the frames it folded (in memory, not in snapshots), so
    that `update_poses` and `remove_frames` can re-fold them (`corrections`); ``checkpoint_every=N``
    also keeps the state after every N-th frame, so that a correction re-folds only the frames after
    the last such state before the first frame it touches. ``undo_depth=D`` keeps undo records of the
    last D folds (`undo`; by default `DEFAULT_UNDO_DEPTH` with ``keep_frames``, else none): a correction of frames among
    them rolls the state back in place (`rollback`) and re-folds from there, so correcting the k most
    recent frames costs about k folds.

    The decoder starts with the parameters of ``config.model`` (`decode.checkpoint.resolve_model`);
    ``load_model=False`` leaves it training-free, for a caller that sets its parameters itself
    (`from_bytes` restores a snapshot's). ``model_sha256`` names the checkpoint file that was loaded.

    Example:
        >>> scene = Scene(SceneConfig(voxel_size=0.01))
        >>> len(scene), scene.frames
        (0, 0)
    """

    def __init__(self, config: SceneConfig, initial_capacity: int = 1 << 15, keep_frames: bool = False,
                 checkpoint_every: int = 0, undo_depth: int | None = None, *, load_model: bool = True):
        if not isinstance(config, SceneConfig):
            raise ValueError(f"config: expected a SceneConfig, got {type(config).__name__}")
        if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int) or checkpoint_every < 0:
            raise ValueError(f"checkpoint_every: expected a non-negative integer, got {checkpoint_every!r}")
        if undo_depth is None:
            undo_depth = DEFAULT_UNDO_DEPTH if keep_frames else 0
        if isinstance(undo_depth, bool) or not isinstance(undo_depth, int) or undo_depth < 0:
            raise ValueError(f"undo_depth: expected a non-negative integer, got {undo_depth!r}")
        self.config = config
        self.appearance = AppearanceUncertainty(config.features.dim)
        self.frames = 0
        self._voxels = VoxelMap(config.features.dim, config.sh_degree, initial_capacity, config.max_voxels)
        self._scratch = Scratch()
        self._front = DepthFrontEnd(config)
        self._history = SeeThroughHistory(config.free_space.history)
        self._keyframes = Keyframes(config.colour_solve.views, config.colour_solve.scale)  # the colour solve's views
        self._decoding = SceneDecoding(config)
        # the trained checkpoint `config.model` names (`decode.checkpoint`); a snapshot brings its own parameters
        checkpoint = _load_model(self._decoding.decoder, config.model) if load_model else None
        self.model_sha256: str | None = checkpoint.sha256 if checkpoint is not None else None
        self._density_sum, self._density_frames = 0.0, 0  # observations per touched voxel, summed over folds
        self._consistency = DepthConsistency()  # consecutive frames' depth compared by depth band (advice only)
        self._lock = threading.Lock()  # the state's lock; `SceneDecoding.lock` is taken before it, never after
        self._generation = 0  # bumped by every fold, so a decode knows whether the state it read is current
        # with keep_frames, the folded frames in order and their arrival indices, for update_poses / remove_frames
        self._kept: list[Frame] | None = [] if keep_frames else None
        self._arrivals: list[int] = []
        # with keep_frames and checkpoint_every, the state after every checkpoint_every-th frame (frame
        # count -> `to_bytes`; each costs the state's bytes in memory): a correction re-folds from the
        # last one before the first frame it touches
        self.checkpoint_every = checkpoint_every if keep_frames else 0
        self._checkpoints: dict[int, bytes] = {}
        self._undo = UndoRing(undo_depth)

    @property
    def decoder(self):
        """The `decode.GaussianDecoder` (its parameters are part of snapshots)."""
        return self._decoding.decoder

    @property
    def label_dim(self) -> int:
        return self._voxels.label_dim

    @property
    def capacity(self) -> int:
        return self._voxels.capacity

    # -- folding ------------------------------------------------------------------------------
    def fold(self, frame: Frame) -> FoldReport:
        """Fold one frame into the scene. Raises ValueError (the scene unchanged) on bad input.

        Frames without depth get it from a plane sweep against the session's recent views (its
        uncertainty becomes the frame's depth std, so reliability follows as with sensor depth).
        """
        t0 = time.perf_counter()
        if not isinstance(frame, Frame):
            raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
        with self._lock:
            return self._fold_kept(frame, self._arrivals[-1] + 1 if self._arrivals else 0, t0)

    def _fold_kept(self, frame: Frame, arrival: int, t0: float) -> FoldReport:
        """`fold` for a caller that holds the scene's lock: the fold with its undo record, then the
        frame kept (with ``keep_frames``) and a checkpoint where one is due."""
        # the fold in progress enters what it overwrites in its undo record, the map's journal
        record = self._voxels.journal = self._undo_record() if self._undo.depth else None
        try:
            report = self._fold(frame, t0)
        finally:
            self._voxels.journal = None
            self._generation += 1
            self._decoding.forget()
        if record is not None:
            if self.label_dim != record.label_dim:  # rows were widened: earlier records no longer fit
                self._undo.clear()
            else:
                self._undo.push(record)
        if self._kept is not None:
            self._arrivals.append(arrival)
            self._kept.append(frame)
            if self.checkpoint_every and self.frames % self.checkpoint_every == 0:
                self._checkpoints[self.frames] = self._to_bytes()
        return report

    def _undo_record(self) -> FoldUndo:
        """What the next fold may overwrite, but for the voxels' rows and see-through evidence, which
        its integrations add as they go (see `undo`)."""
        return FoldUndo(self.frames, len(self._voxels), self.label_dim, list(self._front.window.views),
                        list(self._front.pending), (list(self._keyframes.indices), self._keyframes.frames()),
                        (self._density_sum, self._density_frames))

    def keep_undo(self, depth: int) -> None:
        """Keep undo records of the next ``depth`` folds from now on (0: none); the records kept so far
        are dropped (a loaded snapshot has none)."""
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 0:
            raise ValueError(f"undo_depth: expected a non-negative integer, got {depth!r}")
        with self._lock:
            self._undo = UndoRing(depth)

    def preallocate(self, voxels: int) -> None:
        """Commit the memory of ``voxels`` voxels now, as Open3D's VoxelBlockGrid does for its block
        count: folds that grow the scene up to that size then never wait for the system to fault in
        and zero fresh pages (dear on a virtual machine, where a page's first touch goes through the
        hypervisor). The memory counts in `memory_bytes` from now on. A snapshot does not keep it, nor
        does the state a re-fold brings (`update_poses` and `remove_frames` past the undo records,
        `adopt`): call this again after `load` or those. Raises ValueError for a negative count or
        one above ``max_voxels``; the scene and its results are unchanged.

        Example:
            >>> scene = Scene(SceneConfig(voxel_size=0.01))
            >>> scene.preallocate(100_000)
            >>> scene.capacity >= 100_000, len(scene)
            (True, 0)
        """
        with self._lock:
            self._voxels.preallocate(voxels)

    @property
    def undo_floor(self) -> int:
        """The smallest frame count `rollback` can return the scene to (``frames`` when none)."""
        with self._lock:
            return self._undo.floor(self.frames)

    def rollback(self, frames: int) -> None:
        """Return the fused state to what it was after its first ``frames`` frames, exactly (equal
        `digest`), by the undo records of the last folds (``undo_depth``). Folding the stream's later
        frames again then gives the scene they gave before. Kept frames and checkpoints after that
        point are forgotten. Raises ValueError naming ``frames`` if the records do not reach back."""
        if isinstance(frames, bool) or not isinstance(frames, int) or not 0 <= frames <= self.frames:
            raise ValueError(f"frames: expected a frame count in [0, {self.frames}], got {frames!r}")
        with self._decoding.lock, self._lock:
            self._rollback(frames)

    def _rollback(self, frames: int) -> None:
        undone = self._undo.take(frames, self.frames)
        if not undone:
            return
        target = undone[-1]
        carried = self._solution_by_key()
        restore_voxels(self._voxels, undone)
        for record in undone:  # newest first: each push's slot back as it was
            for slot in reversed(record.history):
                restore_history(self._history, slot)
        self._front.window.views, self._front.pending = list(target.window), list(target.pending)
        self._keyframes.indices, self._keyframes._frames = list(target.keyframes[0]), list(target.keyframes[1])
        self._density_sum, self._density_frames = target.density
        self._consistency.forget_previous()  # its counts describe the sensor, which the rollback does not undo
        self.frames = target.frames
        if self._kept is not None:
            del self._kept[frames:], self._arrivals[frames:]
        self._checkpoints = {c: b for c, b in self._checkpoints.items() if c <= frames}
        self._generation += 1
        self._decoding.reset(keep_rows=True)  # in place: what the folds did not touch decodes as before
        self._carry_solution(carried)  # on the voxels that are still there, due for a re-solve

    def _fold(self, frame: Frame, t0: float) -> FoldReport:
        index, points = self.frames, self._voxels.representative_points
        prepared = self._front.prepare(frame, self._check_foldable, points)
        counts = (0, 0, 0, 0) if prepared.pending else self._integrate(prepared.frame)
        self._front.commit(prepared)
        self._keyframes.add(index, frame)  # a waiting frame's colours join the scene once a partner arrives
        self.frames += 1
        also = 0
        if frame.depth is None and not prepared.pending:  # frames that waited for a partner: fold them now, in order
            for waiting in self._front.ready(points):
                self._integrate(waiting)
                also += 1
        gave_nothing = frame.depth is not None and counts[0] == 0
        warnings = depth_warnings(frame.depth, self.config.range.near, self.config.range.far) if gave_nothing else []
        if frame.depth is not None:  # the sensor's depth (as folded: denoised or completed), not a sweep's
            warnings += self._consistency.observe(prepared.frame)
        return FoldReport(index, *counts, ms=(time.perf_counter() - t0) * 1000.0, pending=prepared.pending,
                          also_folded=also, completed_pixels=prepared.completed_pixels, denoised=prepared.denoised,
                          warnings=warnings)

    def _integrate(self, frame: Frame) -> tuple[int, int, int, int]:
        """Evidence, integration and free space of a frame with depth: (observations, new voxels,
        updated voxels, representative switches)."""
        ev = extract_evidence(frame, self.config, self.appearance)
        first_new = len(self._voxels)
        done = integrate(self._voxels, ev, observation_sh_basis(ev, frame.camera, self.config.sh_degree), self.config,
                         self._scratch)
        if self.config.free_space.enabled:
            if self._voxels.journal is not None:
                self._voxels.journal.history.append(history_slot(self._history))
            integrate_free_space(self._voxels, frame, self.config, self._history, first_new)
        if done.touched_voxels:
            self._density_sum += done.observations / done.touched_voxels
            self._density_frames += 1
        return done.observations, done.new_voxels, done.touched_voxels - done.new_voxels, done.representative_switches

    def _check_foldable(self, frame: Frame) -> None:
        """The checks evidence extraction makes that do not need depth (so a waiting frame cannot fail later)."""
        if self.config.features.backend == "client" and frame.features is None:
            raise ValueError("features: this session uses client-supplied features, but the frame carries none")
        if frame.labels is not None and self.label_dim and frame.labels.shape[-1] != self.label_dim:
            raise ValueError(f"labels: expected {self.label_dim} label channels (as earlier frames), got {frame.labels.shape[-1]}")

    # -- corrections --------------------------------------------------------------------------
    def frame_refs(self) -> list[FrameRef]:
        """The kept frames' keys in fold order (arrival index, frame_id); needs ``keep_frames``."""
        with self._lock:
            self._check_keeps_frames("frames")
            return self._refs()

    def _refs(self) -> list[FrameRef]:
        return [FrameRef(a, f.frame_id) for a, f in zip(self._arrivals, self._kept)]

    def update_poses(self, poses: dict[FrameKey, object]) -> None:
        """Give kept frames new camera-to-world poses (``{frame key: c2w [4, 4]}``, keys as in
        `corrections.resolve_frames`), as a SLAM back end revises them at a loop closure.

        The scene then equals one that folded the corrected stream afresh in the same order (equal
        `digest`): the kept frames are re-folded (see `corrections`). Needs ``keep_frames``; raises
        ValueError naming ``poses.<key>`` (unknown frame, NaN, not rigid) with the scene unchanged."""
        with self._decoding.lock, self._lock:
            self._check_keeps_frames("poses")
            self._refold(check_poses(poses, self._refs()), ())

    def remove_frames(self, keys: list[FrameKey]) -> None:
        """Forget kept frames: the scene then equals one that folded the other frames in the same
        order (equal `digest`). Needs ``keep_frames``; raises ValueError naming ``frames.<key>`` for a
        frame it does not keep, with the scene unchanged. The others keep their arrival indices."""
        if isinstance(keys, (str, int)) or not isinstance(keys, (list, tuple, set)):
            raise ValueError(f"frames: expected a list of frame keys, got {type(keys).__name__}")
        with self._decoding.lock, self._lock:
            self._check_keeps_frames("frames")
            self._refold({}, resolve_frames(keys, self._refs(), "frames"))

    def _refold(self, poses: dict[int, np.ndarray], removed) -> None:
        """Fold the kept frames (``poses`` by position applied, ``removed`` positions left out) and
        adopt the result; the caller holds the decode lock and the scene's lock. The frames before
        the first one touched are unchanged, so the re-fold starts from the last checkpoint before it
        (exact: a checkpoint round-trips the state bit for bit) and re-folds the rest."""
        removed = set(removed)
        first = min(set(poses) | removed)
        frames = list(corrected_stream(self._kept, poses, removed))
        arrivals = [a for k, a in enumerate(self._arrivals) if k not in removed]
        carried = self._solution_by_key()
        if first >= self._undo.floor(self.frames):
            self._refold_in_place(first, frames, arrivals)
        else:
            self._refold_from_checkpoint(first, frames, arrivals)
        self._carry_solution(carried)

    def _refold_from_checkpoint(self, first: int, frames: list[Frame], arrivals: list[int]) -> None:
        """`_refold` past the undo records: from the last checkpoint before ``first``, adopted."""
        start = max((c for c in self._checkpoints if c <= first), default=0)
        base = Scene.from_bytes(self._checkpoints[start]) if start else None
        checkpoints = {c: b for c, b in self._checkpoints.items() if c <= start}
        if base is not None:
            base.keep_undo(self._undo.depth)
        scene = Scene.refolded(self.config, frames[start:], self.appearance, base, self.checkpoint_every, checkpoints,
                               self._undo.depth)
        self._adopt(scene)
        self._kept, self._arrivals, self._checkpoints = frames, arrivals, checkpoints

    def _refold_in_place(self, first: int, frames: list[Frame], arrivals: list[int]) -> None:
        """Roll back to the state after ``first`` frames and fold ``frames[first:]`` on it. If a fold
        fails (a corrected pose that takes the scene past ``max_voxels``), the old frames are folded
        again (they folded before), so the scene is as it was."""
        old_frames, old_arrivals = self._kept[first:], self._arrivals[first:]
        self._rollback(first)
        try:
            for frame, arrival in zip(frames[first:], arrivals[first:]):
                self._fold_kept(frame, arrival, time.perf_counter())
        except Exception:
            self._rollback(first)
            for frame, arrival in zip(old_frames, old_arrivals):
                self._fold_kept(frame, arrival, time.perf_counter())
            raise

    @classmethod
    def refolded(cls, config: SceneConfig, frames, appearance: AppearanceUncertainty | None = None,
                 base: "Scene | None" = None, checkpoint_every: int = 0,
                 checkpoints: dict[int, bytes] | None = None, undo_depth: int = 0) -> "Scene":
        """A scene that folded ``frames`` in order: a fresh one, or ``base`` (a scene that folded the
        stream's earlier frames) folding on; with ``appearance`` (a scene's learned appearance
        uncertainty) in place of its own. With ``checkpoint_every``, the state after every such frame
        count goes into ``checkpoints``; with ``undo_depth``, a fresh scene keeps undo records of its
        last folds (`rollback`)."""
        scene = base if base is not None else cls(config, undo_depth=undo_depth)
        if appearance is not None:
            scene.appearance = appearance
        for frame in frames:
            scene.fold(frame)
            if checkpoint_every and checkpoints is not None and scene.frames % checkpoint_every == 0:
                checkpoints[scene.frames] = scene.to_bytes()
        return scene

    def adopt(self, other: "Scene") -> None:
        """Take ``other``'s fused state (a re-fold of this scene's corrected frames) in one step; this
        scene's decoder, appearance module and kept frames stay. A decode in progress finishes on the
        old state (it took the decode lock first); the next one sees the new state."""
        if other.config != self.config:
            raise ValueError("other: a scene with another config")
        with self._decoding.lock, self._lock:
            self._adopt(other)

    def carry_colour_solution(self, other: "Scene") -> None:
        """Start this scene's colour solve from ``other``'s last solution, where ``other`` is the same
        stream before a correction: its offsets go to the voxels with the same keys here, and the next
        decode re-solves from them (`SceneConfig.colour_solve.refresh`) instead of solving from zero.
        Nothing happens where ``other`` has no solution or this scene keeps no views. A rollback and a
        correction of this scene (`update_poses`, `remove_frames`) carry its own solution so."""
        with other._lock:
            carried = other._solution_by_key()
        with self._decoding.lock, self._lock:
            self._carry_solution(carried)

    def _solution_by_key(self) -> tuple[np.ndarray, torch.Tensor] | None:
        """The colour solution as (voxel keys, offsets), which outlive a re-fold's rows; the caller holds
        the scene's lock."""
        solution = self._decoding.solution
        if solution is None:
            return None
        return self._voxels.state["keys"][solution.rows].copy(), solution.offsets

    def _carry_solution(self, carried: tuple[np.ndarray, torch.Tensor] | None) -> None:
        """`_solution_by_key` of a scene before a correction as this scene's solution, due for a re-solve
        at the next decode; the caller holds the decode lock and the scene's lock."""
        if carried is None or not self.config.colour_solve.views:
            return
        keys, offsets = carried
        rows = self._voxels.find(keys).astype(np.int64)
        found = np.flatnonzero(rows >= 0)
        order = found[np.argsort(rows[found], kind="stable")]
        self._decoding.solution = ColourSolution(rows[order], offsets[torch.from_numpy(order)],
                                                 self.frames - self.config.colour_solve.refresh)

    def _adopt(self, other: "Scene") -> None:
        self.frames, self._voxels, self._scratch, self._front = other.frames, other._voxels, other._scratch, other._front
        self._history, self._keyframes = other._history, other._keyframes
        self._density_sum, self._density_frames = other._density_sum, other._density_frames
        self._consistency = other._consistency
        self._undo = other._undo if other._undo.depth == self._undo.depth else UndoRing(self._undo.depth)
        self._generation += 1
        self._decoding.reset()

    def _check_keeps_frames(self, field: str) -> None:
        if self._kept is None:
            raise ValueError(f"{field}: this scene keeps no frames (create it with keep_frames=True)")

    # -- reading ------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._voxels)

    def sums(self) -> dict[str, np.ndarray]:
        """The raw per-voxel sums (contiguous copies, insertion order, scratch excluded)."""
        return self._voxels.sums()

    def fields(self, sort: bool = True) -> dict[str, torch.Tensor]:
        """Scene fields (see `fields_from_sums`), sorted by voxel key unless ``sort=False``."""
        return fields_from_sums(self.sums(), self.config, sort=sort)

    def observations_per_view(self) -> float:
        """Mean observations one frame adds to a voxel it touches (pixels per voxel footprint, holes
        included). With `support_unit` it makes R_scene's decoding unit "one typical view", so opacity
        does not depend on image resolution or voxel size, only on how many views support a voxel."""
        return self._density_sum / self._density_frames if self._density_frames else 1.0

    def decode_inputs(self) -> DecodeInputs:
        """What `decode_from` needs of the scene, copied: later folds do not change it. A copy of every
        sum; `gaussians` copies under the scene's lock only what its decode reads."""
        with self._lock:
            return self._decode_inputs()

    def _decode_inputs(self, live: bool = False) -> DecodeInputs:
        """`decode_inputs`; with ``live``, views of the state itself, for a decode's `take` under the lock."""
        v = self._voxels
        state = v.state if live else v.copied_state()
        changed_at = v.changed_at[: len(v)]
        return DecodeInputs(v.sums_of(state), functools.partial(gathered_sums, state, v.layout),
                            self.observations_per_view(), self._keyframes.frames(),
                            changed_at if live else changed_at.copy(), self.frames)

    def decode(self, max_gaussians: int | None = None, min_support: float = 0.0, features: bool = True) -> Gaussians:
        """Gaussians of every voxel with R_scene > ``min_support``; with ``max_gaussians``, the
        best-supported ones (level of detail). With ``colour_solve.views``, their colours are then
        solved against the kept input views (`decode.solve_colours`); without ``features``, they carry
        no F_scene (see `gaussians`). The same as ``decode_from(decode_inputs(), ...)``, without the
        copy of every sum: as `gaussians`, it holds the scene's lock only to take what its decode
        reads, so folds go on meanwhile."""
        with self._decoding.lock:
            with self._lock:
                work = self._decoding.take(self._decode_inputs(live=True), max_gaussians, min_support, features)
            return self._decoding.finish(work)

    def decode_from(self, inputs: DecodeInputs, max_gaussians: int | None = None, min_support: float = 0.0,
                    features: bool = True) -> Gaussians:
        """`decode` of the scene as it was when ``inputs`` were taken (`decode_inputs` of this scene).

        Each decode keeps what it made of every voxel (`decoded.DecodedRows`), and the next one
        decodes again only the voxels whose sums a fold has changed since; opacities are recomputed
        for all. So a decode after a fold costs what the fold touched, not the scene, and equals a
        decode from scratch (``inputs._replace(changed_at=None)``). Decodes of one scene take turns
        (they share those rows); folds do not wait for them.
        """
        return self._decoding.decode(inputs, max_gaussians, min_support, features)

    def gaussians(self, max_gaussians: int | None = None, colour_solver: Executor | None = None,
                  features: bool = True) -> Gaussians:
        """`decode(max_gaussians)` of the scene as it is now, decoded once per change: until the next
        fold, later calls (from any thread) return the same Gaussians. Concurrent calls on an
        unchanged scene decode once. The decode holds the scene's lock only to pick the rows that
        decode and copy what it reads of them (the sums of the rows it decodes afresh, F_scene of
        the others: a fold's worth, not the scene), so folds go on meanwhile, and a decode that a
        fold overtook answers its caller but is not kept.

        With ``colour_solver``, a colour re-solve that falls due (`SceneConfig.colour_solve.refresh`)
        runs on that executor (on another thread: it takes the decode lock this call holds) instead of
        in this call, which shows the last solution meanwhile; once it lands, the next call decodes
        with it (`colour_solve_pending` is its future). A service does so, so that a render never
        waits for a re-solve.

        Without ``features`` the Gaussians may carry no F_scene (``features`` None; kept Gaussians
        that carry it are returned as they are): for renders of colour, depth or labels, whose decode
        after a fold then reads only the voxels the fold touched and the columns that pick the
        decoded voxels, not F_scene of every decoded voxel."""
        with self._lock:
            hit = self._decoding.cached(self._lod(max_gaussians), features)
        if hit is not None:
            return hit
        with self._decoding.lock:  # one decode at a time: a second caller waits, then finds it kept
            with self._lock:
                lod = self._lod(max_gaussians)  # the scene may have grown while we waited
                hit = self._decoding.cached(lod, features)
                if hit is not None:
                    return hit
                work = self._decoding.take(self._decode_inputs(live=True), lod, features=features)
                generation = self._generation
            solver = (colour_solver, self._forget_decoded) if colour_solver is not None else None
            gaussians = self._decoding.finish(work, solver)
            with self._lock:
                if self._generation == generation:
                    self._decoding.keep(lod, gaussians)
            return gaussians

    def _forget_decoded(self) -> None:
        """A colour re-solve landed: the decoded Gaussians kept for this state show the last one."""
        with self._lock:
            self._decoding.forget()

    def colour_solve_pending(self) -> Future | None:
        """The future of the last colour re-solve that `gaussians` started on its ``colour_solver``."""
        return self._decoding.pending

    def _lod(self, max_gaussians: int | None) -> int | None:
        """The level of detail ``max_gaussians`` means now: None when it leaves out nothing."""
        if max_gaussians is not None and max_gaussians < 0:
            raise ValueError(f"max_gaussians: expected a non-negative integer, got {max_gaussians}")
        return None if max_gaussians is not None and max_gaussians >= len(self) else max_gaussians

    def _snapshot_arrays(self, sums: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Every array of the fused state: sums (``sums``, else copies of them), free-space history,
        source window, waiting frames, the colour solve's kept views."""
        arrays = {f"state.{k}": v for k, v in (self.sums() if sums is None else sums).items()}
        arrays |= {f"history.{k}": v for k, v in self._history.to_arrays().items()}
        arrays |= self._front.to_arrays()
        if self._keyframes.capacity:  # scenes without the colour solve keep their earlier digests
            arrays |= {f"keyframes.{k}": v for k, v in self._keyframes.to_arrays().items()}
        return arrays

    def digest(self) -> str:
        """sha256 of the whole fused state (sums, free-space history, frame count): equal iff two
        scenes would decode and fold on identically."""
        with self._lock:
            h = hashlib.sha256(f"frames={self.frames}|labels={self.label_dim}|density={self._density_sum!r},{self._density_frames}|".encode())
            for name, array in sorted(self._snapshot_arrays().items()):
                h.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
                h.update(np.ascontiguousarray(array).tobytes())
            return h.hexdigest()

    def memory_bytes(self) -> int:
        """Bytes the scene holds: its state, the colour solve's kept views, the decoded rows and the
        undo records (`undo_bytes`)."""
        return int(self._voxels.nbytes() + self._keyframes.nbytes() + self._decoding.nbytes() + self._undo.nbytes())

    def undo_bytes(self) -> int:
        """Bytes of the undo records kept for `rollback` (part of `memory_bytes`)."""
        with self._lock:
            return self._undo.nbytes()

    def bytes_per_voxel(self) -> float:
        """State bytes per stored voxel: one row of every per-voxel array plus the hash table's bytes
        per stored voxel (`memory_bytes` also counts rows written and since rolled back)."""
        return self._voxels.bytes_per_voxel()

    def stats(self) -> dict:
        return {"frames": self.frames, "voxels": len(self), "memory_bytes": self.memory_bytes(),
                "capacity": self.capacity, "label_dim": self.label_dim,
                "inconsistent_depth_below": self._consistency.limit()}

    # -- persistence --------------------------------------------------------------------------
    def to_bytes(self) -> bytes:
        """One self-contained, versioned snapshot (an .npz with a JSON header)."""
        with self._lock:
            header, arrays = self._snapshot_parts()
        return self._encode(header, arrays)

    def snapshot_parts(self) -> tuple[dict, dict[str, np.ndarray]]:
        """What `to_bytes` writes, as (header, arrays) copied under the scene's lock: later folds do
        not change them, so `encode_snapshot` of them, run while the scene folds on, gives the bytes
        `to_bytes` gave now (a snapshot written off the fold path)."""
        with self._lock:
            # the sums as views into one block copy of the records (a copy per field would read every
            # record once per field); the encoding makes them contiguous off the lock, to the same bytes
            header, arrays = self._snapshot_parts(self._voxels.sums_of(self._voxels.copied_state()))
            # the rest (history, source window, kept views) are views of the live state: copied
            arrays = {k: v if k.startswith("state.") else np.array(v, copy=True) for k, v in arrays.items()}
            return header, arrays | self._model_arrays()

    @staticmethod
    def encode_snapshot(header: dict, arrays: dict[str, np.ndarray], out: BinaryIO | None = None) -> bytes | None:
        """The snapshot's bytes (an .npz with a JSON header) of `snapshot_parts`; with ``out`` (a
        binary file) written there instead of returned, with no copy of the whole in memory."""
        buf = io.BytesIO() if out is None else out
        np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
        return buf.getvalue() if out is None else None

    def _to_bytes(self) -> bytes:
        """`to_bytes`, for a caller that holds the scene's lock."""
        return self._encode(*self._snapshot_parts())

    def _snapshot_parts(self, sums: dict[str, np.ndarray] | None = None) -> tuple[dict, dict[str, np.ndarray]]:
        header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": self.config.to_dict(),
                  "frames": self.frames, "label_dim": self.label_dim, "voxels": len(self),
                  "pending": len(self._front.pending), "density": [self._density_sum, self._density_frames],
                  "model": {"setting": self.config.model, "sha256": self.model_sha256}}
        arrays = self._snapshot_arrays(sums) | {f"consistency.{k}": v for k, v in self._consistency.to_arrays().items()}
        solution = self._decoding.solution
        if solution is not None:  # not in the digest: decodes made it of the state, and they may differ in when
            arrays |= {f"colour_solution.{k}": v for k, v in solution.to_arrays().items()}
        return header, arrays

    def _encode(self, header: dict, arrays: dict[str, np.ndarray]) -> bytes:
        return self.encode_snapshot(header, arrays | self._model_arrays())

    def _model_arrays(self) -> dict[str, np.ndarray]:
        """The decoder's and the appearance module's parameters, as snapshot arrays (copies)."""
        return {f"{prefix}.{k}": v.detach().cpu().numpy().copy()
                for prefix, module in (("decoder", self.decoder), ("appearance", self.appearance))
                for k, v in module.state_dict().items()}

    def save(self, path: str | os.PathLike) -> None:
        """Write the snapshot atomically (temp file, fsync, rename, fsync of the folder)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(self.to_bytes())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)  # the rename itself must survive a crash
        finally:
            os.close(folder)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Scene":
        try:
            npz = np.load(io.BytesIO(data), allow_pickle=False)
            header = json.loads(npz["header"].tobytes().decode())
        except Exception as exc:  # any decoding failure means "not one of our snapshots"
            raise ValueError(f"snapshot: not a readable scene file ({exc})") from None
        if header.get("format") != FORMAT_NAME:
            raise ValueError(f"snapshot: unknown format {header.get('format')!r}")
        if header.get("version") not in (3, FORMAT_VERSION):
            raise ValueError(f"snapshot: version {header.get('version')} is not supported (expected 3 or {FORMAT_VERSION})")
        # the decoder's parameters come from the snapshot, not from the model file (which may be gone)
        scene = cls(SceneConfig.from_dict(header["config"]), initial_capacity=max(int(header["voxels"]), 16),
                    load_model=False)
        scene.model_sha256 = (header.get("model") or {}).get("sha256")
        if header["label_dim"]:
            scene._voxels.set_label_dim(int(header["label_dim"]))
        scene._voxels.load_sums({k[len("state."):]: npz[k] for k in npz.files if k.startswith("state.")})
        scene.frames = int(header["frames"])
        density_sum, density_frames = header.get("density", [0.0, 0])
        scene._density_sum, scene._density_frames = float(density_sum), int(density_frames)
        scene._history = SeeThroughHistory.from_arrays(
            scene.config.free_space.history, {k[len("history."):]: npz[k] for k in npz.files if k.startswith("history.")})
        scene._front.load_arrays(npz, int(header.get("pending", 0)))
        scene._consistency = DepthConsistency.from_arrays(
            {k[len("consistency."):]: npz[k] for k in npz.files if k.startswith("consistency.")})
        scene._keyframes = Keyframes.from_arrays(scene.config.colour_solve.views, scene.config.colour_solve.scale,
                                                 {k[len("keyframes."):]: npz[k] for k in npz.files if k.startswith("keyframes.")})
        for prefix, module in (("decoder", scene.decoder), ("appearance", scene.appearance)):
            module.load_state_dict({k: torch.from_numpy(npz[f"{prefix}.{k}"].copy()) for k in module.state_dict()})
        if "colour_solution.rows" in npz.files:
            scene._decoding.solution = ColourSolution.from_arrays(
                {k[len("colour_solution."):]: npz[k] for k in npz.files if k.startswith("colour_solution.")})
        return scene

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Scene":
        return cls.from_bytes(Path(path).read_bytes())

    def __repr__(self) -> str:
        return f"Scene(frames={self.frames}, voxels={len(self)}, voxel_size={self.config.voxel_size})"
