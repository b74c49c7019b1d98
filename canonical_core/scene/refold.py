"""Re-folds: how a correction of a scene's kept frames (`Scene.update_poses`, `Scene.remove_frames`)
and a rollback (`Scene.rollback`) change its fused state.

A correction re-folds the corrected stream (why: see `corrections`) from an exact state before the
first frame it touches: where the undo records reach back that far (`undo`), the scene is rolled back
in place and folds on, so correcting the k most recent frames costs about k folds; else the last
checkpoint before it (a snapshot, exact bit for bit) folds on into a new scene, which the scene
adopts (`adopt`). Either way the colour solution is carried across by voxel key (rows move in a
re-fold, keys do not), so the next decode re-solves from it instead of from zero.

The functions that change a scene's state expect the caller to hold its decode lock and its lock,
in that order (`Scene` takes them); `refolded` folds a scene no one else sees yet.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..evidence import AppearanceUncertainty
from ..frame import Frame
from ..config import SceneConfig
from .corrections import corrected_stream
from .decoding import ColourSolution
from .folding import fold_kept
from .undo import UndoRing, undo_folds

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["adopt", "carry_solution", "refold", "refolded", "roll_back", "solution_by_key"]


def roll_back(scene: Scene, frames: int) -> None:
    """`Scene.rollback` to the state after the first ``frames`` frames (ValueError if the undo records
    do not reach back)."""
    undone = scene._undo.take(frames, scene.frames)
    if not undone:
        return
    carried = solution_by_key(scene)
    undo_folds(scene, undone)
    scene._consistency.forget_previous()  # its counts describe the sensor, which the rollback does not undo
    if scene._kept is not None:
        del scene._kept[frames:], scene._arrivals[frames:]
    scene._checkpoints = {c: b for c, b in scene._checkpoints.items() if c <= frames}
    scene._generation += 1
    scene._decoding.reset(keep_rows=True)  # in place: what the folds did not touch decodes as before
    carry_solution(scene, carried)  # on the voxels that are still there, due for a re-solve


def refold_after(scene: Scene, first: int, frames: Iterable[Frame]) -> None:
    """`Scene.rollback` to ``first`` frames, then a `Scene.fold` of each of ``frames``, as one step:
    the decode lock and the state's lock are held throughout (as `Scene.update_poses` holds them), so a
    decode, a mesh, a digest or a snapshot sees the scene before or after, never a state between (a
    service's correction of its recent frames; readers wait for its folds). A fold that raises leaves
    the scene rolled back with the frames before it folded (the caller folds the old ones again)."""
    if isinstance(first, bool) or not isinstance(first, int) or not 0 <= first <= scene.frames:
        raise ValueError(f"first: expected a frame count in [0, {scene.frames}], got {first!r}")
    with scene._decoding.lock, scene._lock:
        roll_back(scene, first)
        for frame in frames:
            if not isinstance(frame, Frame):
                raise ValueError(f"frames: expected Frames, got {type(frame).__name__}")
            fold_kept(scene, frame, scene._arrivals[-1] + 1 if scene._arrivals else 0, time.perf_counter())


def refold(scene: Scene, poses: dict[int, np.ndarray], removed: Iterable[int]) -> None:  # poses: position -> c2w [4, 4]
    """Fold the kept frames (``poses`` by position applied, ``removed`` positions left out) and
    adopt the result. The frames before the first one touched are unchanged, so the re-fold starts
    from the last checkpoint before it (exact: a checkpoint round-trips the state bit for bit) and
    re-folds the rest."""
    removed = set(removed)
    if not poses and not removed:  # `update_poses` names no frame before it comes here; `remove_frames([])` does
        raise ValueError("frames: names no frame")
    first = min(set(poses) | removed)
    frames = list(corrected_stream(scene._kept, poses, removed))
    arrivals = [a for k, a in enumerate(scene._arrivals) if k not in removed]
    carried = solution_by_key(scene)
    if first >= scene._undo.floor(scene.frames):
        _refold_in_place(scene, first, frames, arrivals)
    else:
        _refold_from_checkpoint(scene, first, frames, arrivals)
    carry_solution(scene, carried)


def _refold_from_checkpoint(scene: Scene, first: int, frames: list[Frame], arrivals: list[int]) -> None:
    """`refold` past the undo records: from the last checkpoint before ``first``, adopted."""
    start = max((c for c in scene._checkpoints if c <= first), default=0)
    base = type(scene).from_bytes(scene._checkpoints[start]) if start else None
    checkpoints = {c: b for c, b in scene._checkpoints.items() if c <= start}
    if base is None:
        base = type(scene)(scene.config)
    base.keep_undo(scene._undo.depth, scene._undo.max_share)
    refold_scene = refolded(type(scene), scene.config, frames[start:], scene.appearance, base, scene.checkpoint_every,
                            checkpoints)
    adopt(scene, refold_scene)
    scene._kept, scene._arrivals, scene._checkpoints = frames, arrivals, checkpoints


def _refold_in_place(scene: Scene, first: int, frames: list[Frame], arrivals: list[int]) -> None:
    """Roll back to the state after ``first`` frames and fold ``frames[first:]`` on it. If a fold
    fails (a corrected pose that takes the scene past ``max_voxels``), the old frames are folded
    again (they folded before), so the scene is as it was."""
    old_frames, old_arrivals = scene._kept[first:], scene._arrivals[first:]
    roll_back(scene, first)
    try:
        for frame, arrival in zip(frames[first:], arrivals[first:]):
            fold_kept(scene, frame, arrival, time.perf_counter())
    except Exception:
        roll_back(scene, first)
        for frame, arrival in zip(old_frames, old_arrivals):
            fold_kept(scene, frame, arrival, time.perf_counter())
        raise


def refolded(scene_type: type[Scene], config: SceneConfig, frames, appearance: AppearanceUncertainty | None = None,
             base: Scene | None = None, checkpoint_every: int = 0, checkpoints: dict[int, bytes] | None = None,
             undo_depth: int = 0) -> Scene:
    """A scene that folded ``frames`` in order (`Scene.refolded`, ``scene_type`` its class): a fresh
    one, or ``base`` (a scene that folded the stream's earlier frames) folding on; with ``appearance`` (a
    scene's learned appearance uncertainty) in place of its own. With ``checkpoint_every``, the state
    after every such frame count goes into ``checkpoints``; with ``undo_depth``, a fresh scene keeps
    undo records of its last folds (`Scene.rollback`)."""
    scene = base if base is not None else scene_type(config, undo_depth=undo_depth)
    if appearance is not None:
        scene.appearance = appearance
    for frame in frames:
        scene.fold(frame)
        if checkpoint_every and checkpoints is not None and scene.frames % checkpoint_every == 0:
            checkpoints[scene.frames] = scene.to_bytes()
    return scene


def adopt(scene: Scene, other: Scene) -> None:
    """`Scene.adopt`: ``other``'s fused state in ``scene``, whose decoder, appearance module and kept
    frames stay; the decoded rows are dropped (they describe the old state)."""
    scene.frames, scene._voxels = other.frames, other._voxels
    scene._front, scene._history, scene._keyframes = other._front, other._history, other._keyframes
    scene._density_sum, scene._density_frames = other._density_sum, other._density_frames
    scene._consistency = other._consistency
    same = (other._undo.depth, other._undo.max_share) == (scene._undo.depth, scene._undo.max_share)
    scene._undo = other._undo if same else UndoRing(scene._undo.depth, scene._undo.max_share)
    scene._generation += 1
    scene._decoding.reset()


def solution_by_key(scene: Scene) -> tuple[np.ndarray, torch.Tensor] | None:  # ([S] int64 keys, [S, K, 3] offsets)
    """The colour solution as (voxel keys, offsets), which outlive a re-fold's rows; the caller holds
    the scene's lock."""
    solution = scene._decoding.solution
    if solution is None:
        return None
    return scene._voxels.state["keys"][solution.rows].copy(), solution.offsets


def carry_solution(scene: Scene, carried: tuple[np.ndarray, torch.Tensor] | None) -> None:
    """`solution_by_key` of a scene before a correction as ``scene``'s solution, due for a re-solve at
    the next decode."""
    if carried is None or not scene.config.colour_solve.views:
        return
    keys, offsets = carried
    rows = scene._voxels.find(keys).astype(np.int64)
    found = np.flatnonzero(rows >= 0)
    order = found[np.argsort(rows[found], kind="stable")]
    scene._decoding.solution = ColourSolution(rows[order], offsets[torch.from_numpy(order)],
                                              scene.frames - scene.config.colour_solve.refresh)
