"""The track of a session's input cameras: what the web viewer draws as frustums and snaps to.

``cameras.f64`` in the session's folder holds one row of `CAMERA_COLUMNS` float64 per frame the
session holds, so that the track outlives a restart. The session appends a frame's row under its
lock once the frame is durable (before it is acknowledged), and a pose correction rewrites the file
with the corrected poses and without the removed frames, renumbered as the scene now numbers them,
before the session's files catch up with the correction: a restart that finds the correction in the
archive only re-folds the archive's frames and writes the track from their cameras (`write_track`).
The track is a view aid, not scene state: a missing or short file only means fewer frustums.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from canonical_core import Camera, Frame

log = logging.getLogger("canonical.track")

CAMERAS_FILE = "cameras.f64"
# frame_index, width, height, fx, fy, cx, cy, then c2w row-major (16)
CAMERA_COLUMNS = 23
ROW_BYTES = CAMERA_COLUMNS * 8


def camera_row(frame_index: int, camera: Camera) -> np.ndarray:  # [CAMERA_COLUMNS] float64
    K, c2w = camera.K64(), camera.c2w64()
    return np.concatenate([[frame_index, camera.width, camera.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2]], c2w.ravel()])


def camera_json(row: np.ndarray) -> dict:
    """One track row -> ``{"frame_index", "width", "height", "K": [fx, fy, cx, cy], "c2w": 16 numbers}``."""
    return {"frame_index": int(row[0]), "width": int(row[1]), "height": int(row[2]),
            "K": [float(x) for x in row[3:7]], "c2w": [float(x) for x in row[7:23]]}


def read_track(path: Path, frames: int) -> np.ndarray:  # [N, CAMERA_COLUMNS] float64
    """The rows of ``path`` for frames the session holds (frame_index < ``frames``); a torn last row
    (a crash mid-append) and rows of frames no longer in the session are left out."""
    try:
        data = np.fromfile(path, np.float64)
    except (OSError, ValueError):
        return np.zeros((0, CAMERA_COLUMNS))
    rows = data[: len(data) // CAMERA_COLUMNS * CAMERA_COLUMNS].reshape(-1, CAMERA_COLUMNS)
    return rows[rows[:, 0] < frames]


def append_camera(folder: Path, frame_index: int, camera: Camera) -> None:
    """Append frame ``frame_index``'s row to the track in ``folder``, unless the track already
    reaches that frame (a frame sent again, answered from its first fold). A torn last row is cut
    off first, so that the rows after it stay aligned. Never raises: a failure is logged."""
    path = folder / CAMERAS_FILE
    try:
        with open(path, "ab") as f:
            size = f.seek(0, os.SEEK_END)
            if size // ROW_BYTES > frame_index:
                return
            if size % ROW_BYTES:
                f.truncate(size - size % ROW_BYTES)
            f.write(camera_row(frame_index, camera).tobytes())
    except OSError as exc:  # a view aid: the fold stands, the frustum is missing
        log.warning("%s: camera %d not recorded (%s)", folder.name, frame_index, exc)


def correct_track(folder: Path, poses: dict[int, np.ndarray], removed: set[int]) -> None:
    """Rewrite the track in ``folder`` after a correction: frame k's pose becomes ``poses[k]``
    (c2w [4, 4]), the frames in ``removed`` leave it, and the others are renumbered as the scene
    numbers them after the removal (k minus the removed frames before it). Keys are stream positions
    before the correction. Replaces the file whole (no reader sees half of it); never raises."""
    rows = read_track(folder / CAMERAS_FILE, frames=np.iinfo(np.int64).max)
    by_index = {int(row[0]): row.copy() for row in rows}  # a frame's last row, should it hold two
    gone = np.array(sorted(removed), np.int64)
    kept = []
    for index in sorted(set(by_index) - set(removed)):
        row = by_index[index]
        if index in poses:
            row[7:23] = np.asarray(poses[index], np.float64).reshape(16)
        row[0] = index - np.searchsorted(gone, index)
        kept.append(row)
    _replace(folder, kept)


def write_track(folder: Path, cameras: list[Camera]) -> None:
    """The track in ``folder`` made anew: frame k's row from ``cameras[k]``; never raises."""
    _replace(folder, [camera_row(k, camera) for k, camera in enumerate(cameras)])


def tracked(frames: Iterable[Frame | None], cameras: list[Camera]) -> Iterator[Frame | None]:
    """``frames`` passed on as they are read, the camera of each (None: not kept) appended to ``cameras``."""
    for frame in frames:
        if frame is not None:
            cameras.append(frame.camera)
        yield frame


def _replace(folder: Path, rows: list[np.ndarray]) -> None:
    """The track file replaced whole by ``rows`` (no reader sees half of it); a failure is logged."""
    path = folder / CAMERAS_FILE
    temporary = path.with_suffix(".tmp")
    try:
        temporary.write_bytes(b"".join(row.tobytes() for row in rows))
        os.replace(temporary, path)
    except OSError as exc:
        log.warning("%s: the camera track was not rewritten (%s)", folder.name, exc)
