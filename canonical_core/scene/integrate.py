"""Integration: one frame's evidence folded into a `VoxelMap`, then its free-space evidence.

Per voxel the map keeps a running representative (its reliability, feature, lifted position and
colour) and the weighted sums of every fused field. A frame is folded in one vectorised pass
(`kernels.fold_kernel`); within the frame the paper's rule is exact.

Re-weighting rule when a more reliable observation replaces a voxel's representative: the sums
gathered so far were weighted by similarity to the *old* representative; they are scaled by
s = max(0, cos(F_old_rep, F_new_rep)) -- evidence that agreed with a representative that itself
disagrees with the new one is discounted as a whole, and evidence consistent with both is kept.
Where a voxel's representative never changes after its first frame this equals `aggregate_batch`
to float tolerance; elsewhere the tests bound the deviation.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import numba
import numpy as np

from ..evidence import FrameEvidence
from ..frame import Frame
from ..config import SceneConfig
from .free_space import (SeeThroughHistory, frame_free_space_kernel, frustum_chunks, history_free_space_kernel,
                         see_through_map)
from .hashing import resolve_kernel, resolve_tables_size, voxel_keys_kernel
from .kernels import fold_kernel
from .undo import RowsBefore
from .voxel_map import VoxelMap


class Integrated(NamedTuple):
    """What `integrate` did to the map."""

    observations: int
    new_voxels: int
    touched_voxels: int  # new ones included
    representative_switches: int


class Scratch:
    """Per-observation work arrays of `integrate`, grown to the largest frame seen and reused. Lent
    to one fold at a time from a pool (`SCRATCH`), whatever the scene: a process holding many scenes
    (the service) keeps as many sets as folds run at once, not one a scene."""

    def __init__(self):
        self.size = 0
        self.tables = np.empty(0, np.int32)  # `resolve_kernel`'s hash tables, grown with the frames and thread count

    def reserve(self, m: int, parts: int) -> None:
        if m > self.size or not self.size:  # allocated on first use, even for a frame with no evidence
            self.size = max(m, 1024)
            for name in ("obs_keys", "frame_keys", "new_keys"):
                setattr(self, name, np.empty(self.size, np.int64))
            for name in ("touched", "best", "head", "tail", "next_obs", "before_slot"):
                setattr(self, name, np.empty(self.size, np.int32))
        if resolve_tables_size(m, parts) > self.tables.shape[0]:
            self.tables = np.empty(resolve_tables_size(self.size, parts), np.int32)


class ScratchPool:
    """The `Scratch` sets no fold is using, lent one a fold (`lend`) and dropped on request (`clear`)."""

    def __init__(self):
        self._spare: list[Scratch] = []
        self._lock = threading.Lock()

    @contextmanager
    def lend(self) -> Iterator[Scratch]:
        with self._lock:
            scratch = self._spare.pop() if self._spare else Scratch()
        try:
            yield scratch
        finally:
            with self._lock:
                self._spare.append(scratch)

    def clear(self) -> int:
        """Drop the spare sets (those in use stay with their folds); returns how many."""
        with self._lock:
            dropped, self._spare = len(self._spare), []
        return dropped


SCRATCH = ScratchPool()


def release_scratch() -> int:
    """Free the integration's spare work arrays (sized for the largest frame folded so far): what a
    process that dropped its scenes calls to give their memory back. Returns how many sets it freed."""
    return SCRATCH.clear()


def integrate(
    voxels: VoxelMap,
    ev: FrameEvidence,
    basis: np.ndarray,  # [M, (sh_degree + 1)^2] SH basis of each observation's view direction
    config: SceneConfig,
) -> Integrated:
    """Fold ``ev`` into ``voxels`` (the aggregation rule). Raises ValueError (a `CapacityError` past
    ``config.max_voxels``, or label channels unlike earlier frames') before changing anything."""
    with SCRATCH.lend() as scratch:
        return _integrate_with(voxels, ev, basis, config, scratch)


def _integrate_with(voxels: VoxelMap, ev: FrameEvidence, basis: np.ndarray, config: SceneConfig,
                    t: Scratch) -> Integrated:
    if ev.labels is not None and voxels.label_dim and ev.labels.shape[1] != voxels.label_dim:
        raise ValueError(f"labels: expected {voxels.label_dim} label channels (as earlier frames), got {ev.labels.shape[1]}")
    m, parts = len(ev), numba.get_num_threads()
    t.reserve(m, parts)
    obs_keys, new_keys = t.obs_keys[:m], t.new_keys[:m]
    inv_voxel = np.float32(1.0 / config.voxel_size)
    voxel_keys_kernel(ev.points, inv_voxel, obs_keys)
    n_touched, n_new, n_obs = resolve_kernel(
        obs_keys, ev.reliability, config.uses_reliability, voxels.table, voxels.state["keys"], parts, t.tables,
        t.frame_keys, t.touched, new_keys, t.best, t.head, t.tail, t.next_obs)
    voxels.check_room(n_new)
    # nothing has changed up to here; from here on the fold cannot fail on input
    if ev.labels is not None and not voxels.label_dim:
        voxels.set_label_dim(ev.labels.shape[1])
    voxels.reserve(len(voxels) + n_new)
    # the records it overwrites, for an undo record: the kernel copies each as it reads it
    journal, stored = voxels.journal, voxels.stored
    before = journal.rows_before(n_touched - n_new, stored) if journal is not None else RowsBefore.room(0, stored)
    s = voxels.state
    labels = ev.labels if ev.labels is not None else np.zeros((m, voxels.label_dim), np.float32)
    work = np.empty((numba.config.NUMBA_NUM_THREADS, voxels.layout.width), np.float32)  # a record per thread
    switches = fold_kernel(
        voxels.table, s["keys"], s["rows"], s["half"], stored.wide_cols, stored.direction, stored.half_cols,
        stored.half_kind, stored.factor_cols, stored.factor_affine, work, s["rep_rgb"], s["n_obs"], len(voxels), voxels.layout.offsets(), config.uses_reliability,
        config.uses_similarity, np.float32(config.sensor.weight_floor), inv_voxel,
        n_touched, t.touched, new_keys, n_new, t.best, t.head, t.next_obs,
        ev.reliability, ev.features, ev.colors, ev.points, basis, labels, ev.labels is not None,
        journal is not None, t.before_slot, before.index, before.rows, before.half, before.rep_rgb, before.n_obs,
    )
    voxels.commit(t.touched[:n_touched], n_new)
    return Integrated(int(n_obs), int(n_new), int(n_touched), int(switches))


def integrate_free_space(voxels: VoxelMap, frame: Frame, config: SceneConfig, history: SeeThroughHistory,
                         first_new: int) -> None:
    """The frame's see-through evidence for every voxel in its frustum (the new ones, from
    ``first_new`` on, included), then the earlier frames' evidence (``history``) for the voxels this
    frame created; the frame's map then joins the history (see `free_space`)."""
    m = see_through_map(frame, config)
    s, n = voxels.state, len(voxels)
    voxel, near = np.float32(config.voxel_size), np.float32(config.range.near)
    chunks = frustum_chunks(voxels, m, config)
    if voxels.journal is not None:  # what it overwrites, for an undo record
        voxels.journal.free_before(s["free"], chunks, first_new)
    frame_free_space_kernel(s["keys"], s["free"], chunks, n, voxel, m.w2c, m.intrinsics, m.threshold, m.weight,
                            np.float32(m.area_scale), near)
    h = history
    if h.count and n > first_new:
        history_free_space_kernel(s["keys"], s["free"], first_new, n, voxel, h.order(), h.w2c, h.intrinsics,
                                  h.threshold, h.weight, h.dims, h.area, near)
    h.push(m)
