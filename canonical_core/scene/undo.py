"""Undo records of the most recent folds: what a correction of recent frames rolls back in place.

A correction re-folds the corrected stream from an exact state before the first frame it touches.
For frames near the scene's end that state is rebuilt from undo records rather than a checkpoint:
each fold keeps what it is about to overwrite, so a correction of the k most recent frames costs
k roll-backs, k folds and a rebuild of the hash table, not a snapshot load and the folds since it.

What a fold overwrites, and what its record keeps of it:

- the rows of the existing voxels it touches (representative, sums, colour, count): their values
  before each integration (`VoxelMap.journal` collects them);
- the see-through evidence ``free`` of every voxel in its frustum: the whole column before the fold
  (4 bytes a voxel);
- the voxels it creates: only how many voxels there were (rolled back by truncation);
- the free-space history's slot each integration writes, the depth front end's source window and waiting frames,
  the colour solve's kept views, the frame count and the observation density (small).

Rolling back restores every array of the fused state bit for bit (`restore`), so the re-fold that
follows gives the same digest as a fold of the corrected stream afresh.

Example:
    >>> ring = UndoRing(depth=2)
    >>> ring.floor(frames=5)  # no record yet: nothing can be rolled back
    5
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .decoded import gather_rows
from .free_space import SeeThroughHistory, update_chunk_boxes_kernel
from .voxel_map import VoxelMap

__all__ = ["FoldUndo", "RowsBefore", "UndoRing"]


@dataclass(frozen=True)
class RowsBefore:
    """Existing voxels' records before one integration overwrote them."""

    index: np.ndarray  # [T] int64 voxel indices
    rows: np.ndarray  # [T, width] float32
    rep_rgb: np.ndarray  # [T, 3] uint8
    n_obs: np.ndarray  # [T] int32


def rows_before(voxels: VoxelMap, touched: np.ndarray) -> RowsBefore:  # touched: [T] int32, -1 = a new voxel
    """What the rows ``touched`` hold now (new voxels, -1, are left out: truncation removes them)."""
    index = touched[touched >= 0].astype(np.int64)
    s = voxels.state
    # on the numba threads: numpy's fancy indexing copies a record at a time on one (a sixth of a fold)
    return RowsBefore(index, *(gather_rows(s[name], index).numpy() for name in ("rows", "rep_rgb", "n_obs")))


@dataclass
class FoldUndo:
    """What one fold overwrote (see the module). ``frames``: the scene's frame count before it."""

    frames: int
    voxels: int
    label_dim: int
    free: np.ndarray  # [voxels] float32
    window: list
    pending: list
    keyframes: tuple[list, list]
    density: tuple[float, int]
    rows: list[RowsBefore] = field(default_factory=list)  # per integration, in order
    history: list[tuple] = field(default_factory=list)  # per history push, in order (`history_slot`)

    def nbytes(self) -> int:
        rows = sum(r.index.nbytes + r.rows.nbytes + r.rep_rgb.nbytes + r.n_obs.nbytes for r in self.rows)
        history = sum(a.nbytes for *_, slot in self.history for a in slot.values())
        return int(self.free.nbytes + rows + history)


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
        for r in reversed(record.rows):
            s = voxels.state
            s["rows"][r.index], s["rep_rgb"][r.index], s["n_obs"][r.index] = r.rows, r.rep_rgb, r.n_obs
    target = undone[-1]
    n, end = target.voxels, len(voxels)
    for array in voxels.state.values():  # rows past the end are zero, as in a map that never held them
        array[n:end] = 0
    voxels.state["free"][:n] = target.free
    voxels.n = n
    voxels.rebuild_table()
    voxels.chunk_lo[:], voxels.chunk_hi[:] = 0, 0
    update_chunk_boxes_kernel(voxels.state["keys"], 0, n, voxels.chunk_lo, voxels.chunk_hi)
    voxels.touch_all()


class UndoRing:
    """The undo records of the last ``depth`` folds, oldest first."""

    def __init__(self, depth: int):
        self.depth = depth
        self.records: deque[FoldUndo] = deque(maxlen=depth or None)

    def __len__(self) -> int:
        return len(self.records)

    def floor(self, frames: int) -> int:
        """The smallest frame count the scene (now holding ``frames``) can be rolled back to."""
        return self.records[0].frames if self.records else frames

    def push(self, record: FoldUndo) -> None:
        if self.depth:
            self.records.append(record)

    def clear(self) -> None:
        self.records.clear()

    def take(self, frames: int, current: int) -> list[FoldUndo]:
        """Remove and return the records of the folds from frame count ``frames`` on (the scene holds
        ``current`` frames), newest first."""
        if frames < self.floor(current):
            raise ValueError(f"frames: the undo records reach back to {self.floor(current)} frames, not {frames}")
        undone = []
        while self.records and self.records[-1].frames >= frames:
            undone.append(self.records.pop())
        return undone

    def nbytes(self) -> int:
        return sum(r.nbytes() for r in self.records)

