"""Pose corrections and frame removal: which frames a correction names, and the corrected stream.

A frame is named by a stable key: the client's ``frame_id`` (a string), or its arrival index (the
position at which it first arrived, an int, or a string of decimal digits that is no frame's id).
The arrival index does not change when earlier frames are removed.

Why a correction re-folds the kept frames rather than un-adding k of them: the fold is not additive.
A voxel's sums are weighted by similarity to its running representative, and re-scaled when a more
reliable observation replaces it, so a frame's share of a sum depends on the frames folded before
it; the free-space history, the depth front end's source window (frames without depth are swept
against their neighbours) and the colour solve's keyframes are order-dependent too. Re-folding the
corrected stream in arrival order is the one way that is exact: the fold is deterministic, so the
corrected scene equals a scene that folded the corrected stream afresh, bit for bit (equal digests).

Example:
    >>> refs = [FrameRef(0, "a"), FrameRef(1, None), FrameRef(2, "7")]
    >>> resolve_frames(["a", 1, "7"], refs, "frames")
    [0, 1, 2]
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from ..calibration import quaternion_to_matrix, validate_pose
from ..frame import Frame

# An arrival index is an int64; a longer run of digits names no frame (and int() of thousands of
# digits is refused by CPython itself).
MAX_ARRIVAL_DIGITS = 19

__all__ = ["FieldError", "FrameKey", "FrameRef", "check_poses", "corrected_stream", "drift_walk", "drifted", "resolve_frames"]

FrameKey = int | str


class FieldError(ValueError):
    """A ValueError ``"field: problem"`` that also carries ``field``: a frame key may hold any
    character (spaces, colons), so the field cannot always be read back from the message."""

    def __init__(self, field: str, problem: str):
        super().__init__(f"{field}: {problem}")
        self.field = field


class FrameRef(NamedTuple):
    """What names one kept frame: its arrival index and its client ``frame_id`` (or None)."""

    arrival: int
    frame_id: str | None


def resolve_frames(keys: Iterable[FrameKey], refs: Sequence[FrameRef], field: str) -> list[int]:
    """Positions in ``refs`` of the frames ``keys`` name, in the order given. Raises ValueError
    ``"field.key: ..."`` for a key that names no kept frame, or a frame named twice."""
    by_id: dict[str, list[int]] = {}
    for k, r in enumerate(refs):
        if r.frame_id is not None:
            by_id.setdefault(r.frame_id, []).append(k)
    by_arrival = {r.arrival: k for k, r in enumerate(refs)}
    positions: list[int] = []
    for key in keys:
        if isinstance(key, bool) or not isinstance(key, (int, str)):
            raise ValueError(f"{field}: frame keys are frame_id strings or arrival indices, got {type(key).__name__}")
        if isinstance(key, str) and key in by_id:
            if len(by_id[key]) > 1:  # a library's frames may share an id (a capture listing one image twice)
                arrivals = [refs[k].arrival for k in by_id[key]]
                raise FieldError(f"{field}.{key}", f"names {len(arrivals)} kept frames (arrival indices {arrivals}); "
                                                   "name the one meant by its arrival index, an integer")
            position = by_id[key][0]
        elif isinstance(key, int) or (key.isascii() and key.isdigit() and len(key) <= MAX_ARRIVAL_DIGITS):
            position = by_arrival.get(int(key))
        else:
            position = None
        if position is None:
            raise FieldError(f"{field}.{key}", "no kept frame has this frame_id or arrival index")
        if position in positions:
            raise FieldError(f"{field}.{key}", "names a frame that another key names too")
        positions.append(position)
    return positions


def check_poses(poses: Mapping[FrameKey, object], refs: Sequence[FrameRef], field: str = "poses") -> dict[int, np.ndarray]:
    """``{key: c2w}`` -> ``{position in refs: c2w float64 [4, 4]}``, every pose checked as a frame's is
    (`camera.validate_pose`: finite, rigid, bottom row [0, 0, 0, 1]). Raises ValueError naming
    ``field.key`` (a `FieldError`) before anything changes."""
    if not isinstance(poses, Mapping):
        raise ValueError(f"{field}: expected a mapping of frame key to a 4x4 camera-to-world matrix")
    if not poses:
        raise ValueError(f"{field}: names no frame")
    keys = list(poses)
    positions = resolve_frames(keys, refs, field)
    checked = {}
    for key, position in zip(keys, positions):
        try:
            checked[position] = validate_pose(poses[key], f"{field}.{key}")
        except ValueError as exc:
            raise FieldError(f"{field}.{key}", str(exc).removeprefix(f"{field}.{key}: ")) from None
    return checked


def corrected_stream(frames: Iterable[Frame], poses: Mapping[int, np.ndarray], removed: Iterable[int] = ()) -> Iterable[Frame]:
    """The frames in order with ``poses`` (position -> c2w [4, 4]) applied and the positions in
    ``removed`` left out; lazy, so a long stream is decoded one frame at a time."""
    removed = set(removed)
    for position, frame in enumerate(frames):
        if position in removed:
            continue
        yield replace(frame, camera=frame.camera.with_pose(poses[position])) if position in poses else frame


def drift_walk(n: int, step: float, angle_deg: float, every: int = 1, seed: int = 0) -> np.ndarray:  # [n, 4, 4]
    """Rigid motions that accumulate as odometry drift does: before every ``every``-th frame (the
    first included) a step of ``step`` metres in a random direction and ``angle_deg`` degrees about
    a random axis is composed onto the walk. Frame k's drifted pose is ``walk[k] @ c2w_k``."""
    rng = np.random.default_rng(seed)
    walk, out = np.eye(4), np.empty((n, 4, 4))
    for k in range(n):
        if k % every == 0:
            axis, direction = rng.standard_normal(3), rng.standard_normal(3)
            half = np.deg2rad(angle_deg) / 2
            motion = np.eye(4)
            motion[:3, :3] = quaternion_to_matrix(np.r_[np.cos(half), np.sin(half) * axis / np.linalg.norm(axis)])
            motion[:3, 3] = step * direction / np.linalg.norm(direction)
            walk = motion @ walk
        out[k] = walk
    return out


def drifted(frames: Sequence[Frame], walk: np.ndarray) -> list[Frame]:
    """The frames with ``walk`` (`drift_walk`) applied to their poses."""
    return [replace(f, camera=f.camera.with_pose(T @ f.camera.c2w64())) for f, T in zip(frames, walk)]
