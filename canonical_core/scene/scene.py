"""Agg, streaming: the scene that folds one frame at a time, a thin facade over its parts.

`Scene` holds the state and its lock; `Scene.fold` runs one frame's fold (`folding`), corrections
and rollbacks re-fold the kept frames (`refold`), snapshots encode and decode the state
(`snapshot`), and `Scene.decode` / `Scene.gaussians` read the map through the decoder side (`decoding`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
import time
from typing import get_args

import numpy as np
import torch

from ..evidence import AppearanceUncertainty, DepthConsistency
from ..frame import Frame
from ..gaussians import Gaussians
from ..decode.checkpoint import load_model as _load_model
from . import choices, folding, refold, snapshot, solving
from ..config import SceneConfig
from .corrections import FrameKey, FrameRef, check_poses, resolve_frames
from .decoding import Colours, DecodeInputs, SceneDecoding, check_decode_arguments
from .depth_frontend import DepthFrontEnd
from .fields import fields_from_sums
from .folding import FoldReport, PreparedFrame
from .free_space import SeeThroughHistory
from .keyframes import Keyframes
from .undo import MIN_KEPT, UndoRing
from .sums import gathered_sums
from .voxel_map import CapacityError, VoxelMap

__all__ = ["CapacityError", "DecodeInputs", "FoldReport", "Scene"]

# folds a scene that keeps its frames can roll back in place: a record costs several times its fold's
# share of the state, so few: those kept whatever their size (correcting the last 5 frames re-folds 5)
DEFAULT_UNDO_DEPTH = MIN_KEPT


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
        config, self.chosen = choices.choose_without_frame(config)  # the rest at the first fold (`choices`)
        self.config = config
        self.appearance = AppearanceUncertainty(config.features.dim)
        self.frames = 0
        self._voxels = VoxelMap(config.features.dim, config.sh_degree, initial_capacity, config.max_voxels)
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
    def fold(self, frame: Frame | PreparedFrame) -> FoldReport:
        """Fold one frame (or a `prepare`d one) into the scene. Raises ValueError (the scene unchanged) on bad input.

        Frames without depth get it from a plane sweep against the session's recent views (its
        uncertainty becomes the frame's depth std, so reliability follows as with sensor depth).
        """
        t0 = time.perf_counter()
        if not isinstance(frame, (Frame, PreparedFrame)):
            raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
        with self._lock:
            return folding.fold_kept(self, frame, self._arrivals[-1] + 1 if self._arrivals else 0, t0)

    prepare = folding.prepare  # a frame's fold begun without the lock, to overlap the folds before it

    def keep_undo(self, depth: int, max_share: float | None = None) -> None:
        """Keep undo records of the next ``depth`` folds from now on (0: none), with ``max_share`` only as
        many as hold at most that share of the map's bytes (`undo.UndoRing`); the records kept so far
        are dropped (a loaded snapshot has none)."""
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 0:
            raise ValueError(f"undo_depth: expected a non-negative integer, got {depth!r}")
        with self._lock:
            self._undo = UndoRing(depth, max_share)

    def preallocate(self, voxels: int) -> None:
        """Commit the memory of ``voxels`` voxels now, as Open3D's VoxelBlockGrid does for its block
        count: folds that grow the scene up to that size then never wait for the system to fault in
        and zero fresh pages (dear on a virtual machine). It counts in `memory_bytes` from now on; a
        snapshot does not keep it, nor does the state a re-fold brings (`update_poses` and
        `remove_frames` past the undo records, `adopt`): call this again after `load` or those. Raises ValueError naming ``voxels`` for a
        negative count, one above ``max_voxels`` or `config.MAX_VOXELS`, or one whose memory the
        system refuses; the scene and its results are unchanged.

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
            refold.roll_back(self, frames)

    # -- corrections (`refold`) ---------------------------------------------------------------
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
            refold.refold(self, check_poses(poses, self._refs()), ())

    def remove_frames(self, keys: list[FrameKey]) -> None:
        """Forget kept frames: the scene then equals one that folded the other frames in the same
        order (equal `digest`). Needs ``keep_frames``; raises ValueError naming ``frames.<key>`` for a
        frame it does not keep, with the scene unchanged. The others keep their arrival indices."""
        if isinstance(keys, (str, int)) or not isinstance(keys, (list, tuple, set)):
            raise ValueError(f"frames: expected a list of frame keys, got {type(keys).__name__}")
        with self._decoding.lock, self._lock:
            self._check_keeps_frames("frames")
            refold.refold(self, {}, resolve_frames(keys, self._refs(), "frames"))

    refolded = classmethod(refold.refolded)  # a scene that folded a stream, fresh or on a base
    refold_after = refold.refold_after  # `rollback`, then folds, as one step for every reader

    def adopt(self, other: "Scene") -> None:
        """Take ``other``'s fused state (a re-fold of this scene's corrected frames) in one step; this
        scene's decoder, appearance module and kept frames stay. A decode in progress finishes on the
        old state (it took the decode lock first); the next one sees the new state."""
        if other.config != self.config:
            raise ValueError("other: a scene with another config")
        with self._decoding.lock, self._lock:
            refold.adopt(self, other)

    def carry_colour_solution(self, other: "Scene") -> None:
        """Start this scene's colour solve from ``other``'s last solution, where ``other`` is the same
        stream before a correction: its offsets go to the voxels with the same keys here, and the next
        decode re-solves from them (`SceneConfig.colour_solve.refresh`) instead of solving from zero.
        Nothing happens where ``other`` has no solution or this scene keeps no views. A rollback and a
        correction of this scene (`update_poses`, `remove_frames`) carry its own solution so."""
        with other._lock:
            carried = refold.solution_by_key(other)
        with self._decoding.lock, self._lock:
            refold.carry_solution(self, carried)

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
        return DecodeInputs(v.sums_of(state), functools.partial(gathered_sums, state, v.stored),
                            self.observations_per_view(), self._keyframes.frames(),
                            changed_at if live else changed_at.copy(), self.frames, v.stamp_epoch)

    def decode(self, max_gaussians: int | None = None, min_support: float = 0.0, features: bool = True) -> Gaussians:
        """Gaussians of every voxel with R_scene > ``min_support``; with ``max_gaussians``, the
        best-supported ones (level of detail). With ``colour_solve_views``, their colours are then
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

    def gaussians(self, max_gaussians: int | None = None, colours: Colours = "solve",
                  features: bool = True) -> Gaussians:
        """`decode(max_gaussians)` of the scene as it is now, decoded once per change: until the next
        fold, later calls (from any thread) return the same Gaussians. Concurrent calls on an
        unchanged scene decode once. The decode holds the scene's lock only to pick the rows that
        decode and copy what it reads of them (the sums of the rows it decodes afresh, F_scene of
        the others: a fold's worth, not the scene), so folds go on meanwhile, and a decode that a
        fold overtook answers its caller but is not kept.

        With ``colours="last"`` it never solves: it shows the last solution (before the first, the
        fused colours); `solve_colours`, run elsewhere, makes the next. A render never waits so.

        Without ``features`` the Gaussians may carry no F_scene (``features`` None; kept Gaussians
        that carry it are returned as they are): for renders of colour, depth or labels, whose decode
        after a fold then reads only the voxels the fold touched and the columns that pick the
        decoded voxels, not F_scene of every decoded voxel."""
        if colours not in get_args(Colours):
            raise ValueError(f"colours: expected one of {list(get_args(Colours))}, got {colours!r}")
        with self._lock:
            hit = self._cached(self._lod(max_gaussians), colours, features)
        if hit is not None:
            return hit
        with self._decoding.lock:  # one decode at a time: a second caller waits, then finds it kept
            with self._lock:
                lod = self._lod(max_gaussians)  # the scene may have grown while we waited
                hit = self._cached(lod, colours, features)
                if hit is not None:
                    return hit
                work = self._decoding.take(self._decode_inputs(live=True), lod, features=features)
                generation = self._generation
            gaussians = self._decoding.finish(work, colours)
            with self._lock:
                if self._generation == generation:
                    self._decoding.keep(lod, gaussians)
            return gaussians

    def _cached(self, lod: int | None, colours: Colours, features: bool) -> Gaussians | None:
        """Kept Gaussians for `gaussians`; none when it solves (they may show an older solution)."""
        if colours == "solve" and len(self._keyframes) > 0 and self._decoding.refresh_due(self.frames):
            return None
        return self._decoding.cached(lod, features)

    # the colour solve off the decode path (`solving`): whether one is due, and the solve
    colour_solve_due, solve_colours, colours_solved_frames = solving.colour_solve_due, solving.solve_colours, solving.colours_solved_frames

    def _lod(self, max_gaussians: int | None) -> int | None:
        """The level of detail ``max_gaussians`` means now: None when it leaves out nothing."""
        check_decode_arguments(max_gaussians, 0.0)
        return None if max_gaussians is not None and max_gaussians >= len(self) else max_gaussians

    def _snapshot_arrays(self, sums: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """Every array of the fused state (`snapshot.state_arrays`), for a caller that holds the lock."""
        return snapshot.state_arrays(self, sums)

    def digest(self) -> str:
        """sha256 of the whole fused state (sums, free-space history, frame count): equal iff two scenes would decode and fold on identically."""
        with self._lock:
            h = hashlib.sha256(f"frames={self.frames}|labels={self.label_dim}|density={self._density_sum!r},{self._density_frames}|".encode())
            for name, array in sorted(self._snapshot_arrays().items()):
                if name.startswith("keyframes.") and name.endswith(".id"):  # a kept view's name: neither folds nor decodes
                    continue
                h.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
                h.update(np.ascontiguousarray(array).tobytes())
            return h.hexdigest()

    def memory_bytes(self) -> int:
        """Bytes the scene holds: state, the colour solve's kept views, decoded rows, undo records."""
        return int(self._voxels.nbytes() + self._keyframes.nbytes() + self._decoding.nbytes() + self._undo.nbytes())

    def undo_bytes(self) -> int:
        """Bytes of the undo records kept for `rollback` (part of `memory_bytes`)."""
        with self._lock:
            return self._undo.nbytes()

    def bytes_per_voxel(self) -> float:
        """State bytes per stored voxel: a row of every per-voxel array and the hash table's share (`memory_bytes` also counts rows written and since rolled back)."""
        return self._voxels.bytes_per_voxel()

    def stats(self) -> dict:
        return {"frames": self.frames, "voxels": len(self), "memory_bytes": self.memory_bytes(),
                "capacity": self.capacity, "label_dim": self.label_dim,
                "inconsistent_depth_below": self._consistency.limit(), "voxel_size": self.config.voxel_size,
                "sensor": self.config.sensor.family, "chosen": dict(self.chosen)}  # `choices`: why these

    # -- persistence (`snapshot`) -------------------------------------------------------------
    def to_bytes(self) -> bytes:
        """One self-contained, versioned snapshot (an .npz with a JSON header)."""
        with self._lock:
            header, arrays = snapshot.snapshot_parts(self)
        return snapshot.encode(self, header, arrays)

    def snapshot_parts(self) -> tuple[dict, dict[str, np.ndarray]]:
        """What `to_bytes` writes, as (header, arrays) copied under the scene's lock: later folds do
        not change them, so `encode_snapshot` of them, run while the scene folds on, gives the bytes
        `to_bytes` gave now (a snapshot written off the fold path)."""
        with self._lock:
            return snapshot.copied_parts(self)

    encode_snapshot = staticmethod(snapshot.encode_snapshot)  # the bytes of `snapshot_parts`

    def save(self, path: str | os.PathLike) -> None:
        """Write the snapshot atomically (temp file, fsync, rename, fsync of the folder)."""
        snapshot.save(self, path)

    from_bytes = classmethod(snapshot.from_bytes)  # the scene a `to_bytes` snapshot holds
    load = classmethod(snapshot.load)  # the scene a `save` file holds
    __reduce__ = snapshot.reduce  # pickle and deepcopy carry the snapshot

    def __repr__(self) -> str:
        return f"Scene(frames={self.frames}, voxels={len(self)}, voxel_size={self.config.voxel_size})"