"""TUM-style captures: poses ``tx ty tz qx qy qz qw`` (camera-to-world, quaternion scalar last).

Two layouts:

- **slambook** (``pose.txt`` + ``color/`` + ``depth/``): line k of ``pose.txt`` is frame k
  (1-based), read from ``color/k.png`` (or .jpg) and ``depth/k.pgm`` (or .png). Default depth
  scale 1000 (millimetres).
- **TUM RGB-D** (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``, each ``timestamp ...`` per line,
  '#' comments): every colour image is paired with the depth image and the pose nearest in time,
  if within ``max_dt`` seconds (0.02 by default); colour images without both are dropped. Default
  depth scale 5000 (TUM's 16-bit PNGs).

In both, a listed frame whose colour or depth image is missing is left out, with one warning that
counts such frames; ``strict=True`` refuses the capture instead.

Neither layout stores the intrinsics: pass ``K`` (3x3 or (fx, fy, cx, cy)), or put a 3x3
``intrinsics.txt`` / ``camera.txt`` in the folder.

Example:
    >>> seq = load_tum("../shared/data/slambook_rgbd5", K=(518.0, 519.0, 325.5, 253.5))  # doctest: +SKIP
    >>> seq.frame_ids  # doctest: +SKIP
    ['1', '2', '3', '4', '5']
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..calibration import quaternion_to_matrix, validate_pose
from .files import (MissingFile, MissingIntrinsics, RGBDFile, SkippedFrames, as_intrinsics, find_one, found_frames,
                    one_size, parse_floats, read_intrinsics_file, read_text, select)
from .images import check_depth_scale
from .sequence import FrameSequence

INTRINSICS_NAMES = ("intrinsics.txt", "camera.txt")
SLAMBOOK_DEPTH_SCALE = 1000.0
TUM_DEPTH_SCALE = 5000.0


def tum_pose_to_matrix(values, field: str) -> np.ndarray:  # [4, 4] float64
    """``tx ty tz qx qy qz qw`` (7 numbers, scalar-last quaternion) -> validated 4x4 camera-to-world."""
    p = np.asarray(values, dtype=np.float64)
    if p.shape != (7,):
        raise ValueError(f"{field}: expected 7 values tx ty tz qx qy qz qw, got {p.shape[0] if p.ndim == 1 else list(p.shape)}")
    if not np.isfinite(p).all() or np.linalg.norm(p[3:]) < 1e-8:
        raise ValueError(f"{field}: expected finite values and a non-zero quaternion, got {p.tolist()}")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(p[[6, 3, 4, 5]])
    T[:3, 3] = p[:3]
    return validate_pose(T, field)


def read_table(path: Path, columns: int) -> list[tuple[str, list[str]]]:
    """Rows of a whitespace-separated text file as (location 'file:line', words); '#' lines skipped.

    Raises ValueError naming the file and line when a row has a different number of columns.
    """
    rows = []
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        if len(words) != columns:
            raise ValueError(f"{path}:{number}: expected {columns} columns, got {len(words)}: {line.strip()!r}")
        rows.append((f"{path}:{number}", words))
    return rows


def _resolve_K(root: Path, K) -> np.ndarray:
    if K is not None:
        return as_intrinsics(K, "K")
    found = find_one([root], INTRINSICS_NAMES)
    if found is None:
        raise MissingIntrinsics(
            f"{root}: camera intrinsics are needed (the capture has none): pass K=(fx, fy, cx, cy) or a 3x3 K of "
            f"the camera that took it, or put a 3x3 {' / '.join(INTRINSICS_NAMES)} in the folder"
        )
    return read_intrinsics_file(found)


def _first_existing(folder: Path, stem: str, suffixes: tuple[str, ...], what: str) -> Path:
    for suffix in suffixes:
        if (folder / (stem + suffix)).is_file():
            return folder / (stem + suffix)
    raise MissingFile(f"{folder / (stem + suffixes[0])}: file not found ({what}; also tried {list(suffixes[1:])})")


def _slambook_sources(root: Path, K: np.ndarray, depth_scale: float, strict: bool) -> list[RGBDFile]:
    def frame(line: tuple[int, tuple[str, list[str]]]) -> RGBDFile:
        k, (location, words) = line
        c2w = tum_pose_to_matrix(parse_floats(words, location), location)
        color = _first_existing(root / "color", str(k), (".png", ".jpg"), f"colour image of pose line {k}")
        depth = _first_existing(root / "depth", str(k), (".pgm", ".png"), f"depth image of pose line {k}")
        return RGBDFile(str(k), color, depth, K, c2w, depth_scale)

    return found_frames(enumerate(read_table(root / "pose.txt", 7), start=1), frame, root / "pose.txt", strict)


def _nearest(times: np.ndarray, queries: np.ndarray, max_dt: float) -> np.ndarray:  # [Q] index or -1
    """Index of the entry of sorted ``times`` nearest each query, -1 when none is within max_dt."""
    right = np.minimum(np.searchsorted(times, queries), len(times) - 1)
    left = np.maximum(right - 1, 0)
    pick = np.where(np.abs(times[left] - queries) <= np.abs(times[right] - queries), left, right)
    return np.where(np.abs(times[pick] - queries) <= max_dt, pick, -1)


def _stamped(path: Path, columns: int) -> tuple[list[tuple[str, list[str]]], np.ndarray]:
    """Rows of a TUM list file sorted by timestamp, and the timestamps [N] (seconds)."""
    rows = read_table(path, columns)
    if not rows:
        raise ValueError(f"{path}: no entries")
    times = np.array([parse_floats(words[:1], location)[0] for location, words in rows])
    order = np.argsort(times, kind="stable")
    return [rows[i] for i in order], times[order]


def _tum_sources(root: Path, K: np.ndarray, depth_scale: float, max_dt: float, strict: bool) -> list[RGBDFile]:
    rgb, rgb_t = _stamped(root / "rgb.txt", 2)
    depth, depth_t = _stamped(root / "depth.txt", 2)
    poses, pose_t = _stamped(root / "groundtruth.txt", 8)
    associated = [(row, d, p) for row, d, p in zip(rgb, _nearest(depth_t, rgb_t, max_dt), _nearest(pose_t, rgb_t, max_dt))
                  if d >= 0 and p >= 0]
    if not associated:
        raise ValueError(f"{root}: no colour image has both a depth image and a pose within {max_dt} s")
    if len(associated) < len(rgb):  # as TUM's associate.py leaves them out; said, as missing files are
        unmatched = f"{len(rgb) - len(associated)} of {len(rgb)} colour images, which have no depth image or pose within {max_dt} s"
        if strict:
            raise ValueError(f"{root / 'rgb.txt'}: {unmatched} (strict)")
        warnings.warn(f"{root / 'rgb.txt'}: skipped {unmatched}; strict=True refuses such a capture", SkippedFrames,
                      stacklevel=4)

    def frame(association) -> RGBDFile:
        (location, (stamp, color)), d, p = association
        pose_location, pose_words = poses[p]
        c2w = tum_pose_to_matrix(parse_floats(pose_words[1:], pose_location), pose_location)
        color_path, depth_path = root / color, root / depth[d][1][1]
        for file, where in ((color_path, location), (depth_path, depth[d][0])):
            if not file.is_file():
                raise MissingFile(f"{file}: file not found (listed at {where})")
        return RGBDFile(stamp, color_path, depth_path, K, c2w, depth_scale)

    return found_frames(associated, frame, root / "rgb.txt", strict)


def load_tum(
    path: str | Path,
    K=None,
    depth_scale: float | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    max_dt: float = 0.02,
    strict: bool = False,
) -> FrameSequence:
    """Load a TUM RGB-D or slambook-style capture as a lazily-read `FrameSequence`.

    Args:
        path: the capture folder.
        K: 3x3 intrinsics or (fx, fy, cx, cy) in pixels; else read from intrinsics.txt / camera.txt.
        depth_scale: raw depth units per metre; None = the layout's default (TUM 5000, slambook 1000).
        stride, max_frames: keep every stride-th frame, at most max_frames of them.
        max_dt: TUM layout only: the largest timestamp gap (s) for pairing colour, depth and pose.
        strict: refuse (ValueError) a listed frame whose colour or depth image is missing; by
            default such frames are left out, with one `SkippedFrames` warning that counts them.

    Returns frames with ``frame_id`` = the colour timestamp (TUM) or the 1-based line number
    (slambook).

    Example:
        >>> seq = load_tum("rgbd_dataset_freiburg1_xyz", K=(517.3, 516.5, 318.6, 255.3))  # doctest: +SKIP
        >>> seq[0].depth.max()  # doctest: +SKIP
    """
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder")
    if depth_scale is not None:
        check_depth_scale(depth_scale)
    if not max_dt >= 0:
        raise ValueError(f"max_dt: expected a non-negative number of seconds, got {max_dt!r}")
    if (root / "groundtruth.txt").is_file():
        sources = _tum_sources(root, _resolve_K(root, K), depth_scale or TUM_DEPTH_SCALE, max_dt, strict)
    elif (root / "pose.txt").is_file():
        sources = _slambook_sources(root, _resolve_K(root, K), depth_scale or SLAMBOOK_DEPTH_SCALE, strict)
    else:
        raise ValueError(f"{root}: neither groundtruth.txt (TUM RGB-D) nor pose.txt (slambook layout) found")
    return FrameSequence(root.name, select(one_size(sources), stride, max_frames))
