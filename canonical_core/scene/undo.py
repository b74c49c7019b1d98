"""Undo records of the most recent folds: what a correction of recent frames rolls back in place.

A correction re-folds the corrected stream from an exact state before the first frame it touches.
For frames near the scene's end that state is rebuilt from undo records rather than a checkpoint:
each fold keeps what it is about to overwrite, so a correction of the k most recent frames costs
k roll-backs and k folds, not a snapshot load and the folds since it.

What a fold overwrites, and what its record keeps of it:

- the records of the existing voxels it touches (representative, sums, colour, count), as the map
  stores them (`stored`): their values before each integration, copied by the fold kernel as it
  reads them (`RowsBefore`);
- the see-through evidence ``free`` of the existing voxels in the chunks its frustum meets, before
  each free-space pass (`FreeBefore`), not the whole column: on a room-scale map most chunks lie
  outside one frame's view;
- the voxels it creates: only how many voxels there were (rolled back by `VoxelMap.truncate`);
- the free-space history's slot each integration writes, the depth front end's source window and waiting frames,
  the colour solve's kept views, the frame count and the observation density (small).

The integration enters the first two in the record (`VoxelMap.journal`) as it goes, in the order it
overwrites them; the roll-back applies them newest first. Rolling back restores every array of the
fused state bit for bit (`restore`), so the re-fold that follows gives the same digest as a fold of
the corrected stream afresh.

Example:
    >>> ring = UndoRing(depth=2)
    >>> ring.floor(frames=5)  # no record yet: nothing can be rolled back
    5
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numba
import numpy as np

from .free_space import CHUNK, SeeThroughHistory
from .stored import StoredRows
from .voxel_map import VoxelMap

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["FoldUndo", "FreeBefore", "RowsBefore", "UndoRing"]


@dataclass(frozen=True)
class RowsBefore:
    """Existing voxels' records before one integration overwrote them."""

    index: np.ndarray  # [T] int64 voxel indices
    rows: np.ndarray  # [T, width] float32, the stored records' float32 part
    half: np.ndarray  # [T, half_width] uint16, their float16 part
    rep_rgb: np.ndarray  # [T, 3] uint8
    n_obs: np.ndarray  # [T] int32

    @classmethod
    def room(cls, count: int, stored: StoredRows) -> "RowsBefore":
        """Room for ``count`` records laid out as ``stored``, for the fold kernel to fill."""
        return cls(np.empty(count, np.int64), np.empty((count, stored.width), np.float32),
                   np.empty((count, stored.half_width), np.uint16), np.empty((count, 3), np.uint8),
                   np.empty(count, np.int32))

    def restore(self, voxels: VoxelMap) -> None:
        s, i = voxels.state, self.index
        s["rows"][i], s["half"][i], s["rep_rgb"][i], s["n_obs"][i] = self.rows, self.half, self.rep_rgb, self.n_obs

    def nbytes(self) -> int:
        return self.index.nbytes + self.rows.nbytes + self.half.nbytes + self.rep_rgb.nbytes + self.n_obs.nbytes


@dataclass(frozen=True)
class FreeBefore:
    """The see-through evidence of voxels [0, ``limit``) in ``chunks`` before one free-space pass
    (voxels from ``limit`` on are new in that fold: the roll-back truncates them)."""

    chunks: np.ndarray  # [C] int32, ascending
    limit: int
    values: np.ndarray  # [C * CHUNK, less the part of the last chunk past limit] float32

    @classmethod
    def of(cls, free: np.ndarray, chunks: np.ndarray, limit: int) -> "FreeBefore":  # free: [V] float32
        """The values of ``free`` that a pass over ``chunks`` will change."""
        chunks = chunks[chunks * CHUNK < limit]  # ascending, so only the last one can reach past limit
        size = 0 if not len(chunks) else (len(chunks) - 1) * CHUNK + min(CHUNK, limit - int(chunks[-1]) * CHUNK)
        values = np.empty(size, np.float32)
        _copy_chunks_kernel(free, chunks, limit, values, True)
        return cls(chunks.copy(), limit, values)

    def restore(self, voxels: VoxelMap) -> None:
        _copy_chunks_kernel(voxels.state["free"], self.chunks, self.limit, self.values, False)

    def nbytes(self) -> int:
        return self.chunks.nbytes + self.values.nbytes


@numba.njit(cache=True, parallel=True)
def _copy_chunks_kernel(free, chunks, limit, values, save):
    """values[c * CHUNK + t] <-> free[chunks[c] * CHUNK + t] for the voxels below ``limit`` (to
    ``values`` when ``save``, back to ``free`` otherwise)."""
    for c in numba.prange(chunks.shape[0]):
        start = chunks[c] * CHUNK
        for t in range(min(CHUNK, limit - start)):
            if save:
                values[c * CHUNK + t] = free[start + t]
            else:
                free[start + t] = values[c * CHUNK + t]


@dataclass
class FoldUndo:
    """What one fold overwrote (see the module). ``frames``: the scene's frame count before it."""

    frames: int
    voxels: int
    label_dim: int
    window: list
    pending: list
    keyframes: tuple[list, list]
    density: tuple[float, int]
    before: list[RowsBefore | FreeBefore] = field(default_factory=list)  # in the order the fold overwrote them
    history: list[tuple] = field(default_factory=list)  # per history push, in order (`history_slot`)

    def rows_before(self, count: int, stored: StoredRows) -> RowsBefore:
        """Room for the ``count`` records that an integration is about to overwrite (`RowsBefore.room`),
        entered in the record."""
        before = RowsBefore.room(count, stored)
        self.before.append(before)
        return before

    def free_before(self, free: np.ndarray, chunks: np.ndarray, limit: int) -> None:
        """Enter the values of ``free`` that a free-space pass over ``chunks`` will change (`FreeBefore.of`)."""
        self.before.append(FreeBefore.of(free, chunks, limit))

    def nbytes(self) -> int:
        history = sum(a.nbytes for *_, slot in self.history for a in slot.values())
        return int(sum(b.nbytes() for b in self.before) + history)


def history_slot(history: SeeThroughHistory) -> tuple:
    """What `SeeThroughHistory.push` will overwrite: the ring's position, the maps' shape, the slot."""
    s = history.head
    slot = {name: getattr(history, name)[s].copy() for name in history._ARRAYS}
    return history.count, history.head, history.threshold.shape, slot


def restore_history(history: SeeThroughHistory, saved: tuple) -> None:
    count, head, shape, slot = saved
    if history.threshold.shape != shape:  # a push widened the maps: the old ones are their top-left corner
        for name in ("threshold", "weight"):
            setattr(history, name, np.ascontiguousarray(getattr(history, name)[:, : shape[1], : shape[2]]))
    for name, value in slot.items():
        getattr(history, name)[head] = value
    history.count, history.head = count, head


def restore_voxels(voxels: VoxelMap, undone: list[FoldUndo]) -> None:
    """Roll ``voxels`` back through ``undone`` (newest first) to the state before the last one's fold."""
    for record in undone:
        for before in reversed(record.before):
            before.restore(voxels)
    n = undone[-1].voxels
    voxels.truncate(n)  # the voxels the folds created
    restored = [b.index[b.index < n] for record in undone for b in record.before if isinstance(b, RowsBefore)]
    voxels.touch(np.concatenate(restored) if restored else np.zeros(0, np.int64))


# the service's bound on its sessions' undo records, as a share of the bytes of the map they undo:
# a deep ring (`undo_depth` up to 1024) costs at most this beside the state, or its newest
# `MIN_KEPT` records where those alone hold more (a capture whose every frame touches most of the map)
MAX_UNDO_SHARE = 0.5
MIN_KEPT = 5  # records kept whatever their size: corrections of the last few frames stay in place


def undo_folds(scene: Scene, undone: list[FoldUndo]) -> None:
    """The fused state as it was before the folds of ``undone`` (their undo records, newest first)."""
    target = undone[-1]
    restore_voxels(scene._voxels, undone)
    for record in undone:  # newest first: each push's slot back as it was
        for slot in reversed(record.history):
            restore_history(scene._history, slot)
    scene._front.window.views, scene._front.pending = list(target.window), list(target.pending)
    scene._keyframes.indices, scene._keyframes._frames = list(target.keyframes[0]), list(target.keyframes[1])
    scene._density_sum, scene._density_frames = target.density
    scene.frames = target.frames


class UndoRing:
    """The undo records of the last ``depth`` folds, oldest first; with ``max_share``, those past
    the newest `MIN_KEPT` only while they all hold at most that share of the map's bytes (`push`)."""

    def __init__(self, depth: int, max_share: float | None = None):
        if max_share is not None and not max_share > 0:
            raise ValueError(f"max_share: expected a positive share of the map's bytes, got {max_share!r}")
        self.depth, self.max_share = depth, max_share
        self.records: deque[FoldUndo] = deque()
        self._sizes: deque[int] = deque()  # each record's bytes, as `nbytes` sums them
        self._bytes = 0

    def __len__(self) -> int:
        return len(self.records)

    def floor(self, frames: int) -> int:
        """The smallest frame count the scene (now holding ``frames``) can be rolled back to."""
        return self.records[0].frames if self.records else frames

    def push(self, record: FoldUndo, map_bytes: int) -> None:
        """Keep ``record``, the newest; then drop the oldest ones while more than ``depth`` are kept, or
        more than `MIN_KEPT` holding more than ``max_share`` of ``map_bytes`` (the map's bytes now)."""
        if not self.depth:
            return
        self.records.append(record)
        self._sizes.append(size := record.nbytes())
        self._bytes += size
        limit = float("inf") if self.max_share is None else self.max_share * map_bytes
        while len(self.records) > self.depth or (len(self.records) > MIN_KEPT and self._bytes > limit):
            self._pop(0)

    def _pop(self, end: int) -> FoldUndo:  # end: 0 the oldest record, -1 the newest
        record = self.records.popleft() if end == 0 else self.records.pop()
        self._bytes -= self._sizes.popleft() if end == 0 else self._sizes.pop()
        return record

    def clear(self) -> None:
        self.records.clear()
        self._sizes.clear()
        self._bytes = 0

    def take(self, frames: int, current: int) -> list[FoldUndo]:
        """Remove and return the records of the folds from frame count ``frames`` on (the scene holds
        ``current`` frames), newest first."""
        if frames < self.floor(current):
            raise ValueError(f"frames: the undo records reach back to {self.floor(current)} frames, not {frames}")
        undone = []
        while self.records and self.records[-1].frames >= frames:
            undone.append(self._pop(-1))
        return undone

    def nbytes(self) -> int:
        return self._bytes

