"""The Redwood / Open3D reconstruction-system layout: ``image/``, ``depth/``, ``trajectory.log``.

- ``image/NNNNN.jpg`` (or .png): 8-bit RGB; ``depth/NNNNN.png``: uint16 in 1/depth_scale metres
  (millimetres by default), 0 = missing, registered to the colour image;
- ``trajectory.log``: per frame a line ``i j n`` (metadata) and then the 4 rows of a 4x4
  camera-to-world matrix, OpenCV axes, metres; its k-th entry belongs to the k-th image in sorted
  file-name order;
- no intrinsics file: the layout's captures use the PrimeSense default (fx = fy = 525,
  cx = 319.5, cy = 239.5, as Open3D assumes), or pass ``intrinsics=``.

Example:
    >>> seq = load_redwood("../shared/data/livingroom_synthetic", stride=20)  # doctest: +SKIP
    >>> seq[0].camera.fx  # doctest: +SKIP
    525.0
"""

from __future__ import annotations

from pathlib import Path

from ..calibration import validate_pose
from .files import as_intrinsics, one_size, parse_floats, posed_images, read_text
from .sequence import FrameSequence

PRIMESENSE_DEFAULT = (525.0, 525.0, 319.5, 239.5)


def is_redwood(root: Path) -> bool:
    return (root / "trajectory.log").is_file() and (root / "image").is_dir()


def read_trajectory_log(path: Path) -> list:  # [N] of [4, 4] float64 camera-to-world
    """The camera-to-world matrices of a ``trajectory.log`` (metadata line + 4 matrix rows per entry)."""
    lines = [line.split() for line in read_text(path).splitlines() if line.strip()]
    if len(lines) % 5:
        raise ValueError(f"{path}: {len(lines)} non-empty lines; expected 5 per frame (a metadata line and 4 rows)")
    poses = []
    for k in range(0, len(lines), 5):
        rows = lines[k + 1 : k + 5]
        if any(len(row) != 4 for row in rows):
            raise ValueError(f"{path}:{k + 2}: expected 4 rows of 4 numbers after the metadata line {' '.join(lines[k])!r}")
        where = f"{path}:{k + 2}"
        poses.append(validate_pose(parse_floats([w for row in rows for w in row], where).reshape(4, 4), where))
    return poses


def load_redwood(
    path: str | Path,
    intrinsics=PRIMESENSE_DEFAULT,
    depth_scale: float = 1000.0,
    stride: int = 1,
    max_frames: int | None = None,
) -> FrameSequence:
    """Load a Redwood / Open3D folder as a lazily-read `FrameSequence`.

    Args:
        path: the capture folder (``image/``, ``depth/``, ``trajectory.log``).
        intrinsics: 3x3 K or (fx, fy, cx, cy) in pixels (default: the PrimeSense default).
        depth_scale: raw depth units per metre (1000 for millimetres).
        stride, max_frames: keep every stride-th frame, at most max_frames of them.

    Returns frames with ``frame_id`` = the image's file stem, in file-name order.
    """
    root = Path(path)
    if not is_redwood(root):
        raise ValueError(f"{root}: not a Redwood / Open3D folder (expected image/ and trajectory.log)")
    sources = posed_images(root / "image", root / "depth", as_intrinsics(intrinsics),
                           read_trajectory_log(root / "trajectory.log"), depth_scale, stride, max_frames,
                           root / "trajectory.log")
    return FrameSequence(root.name, one_size(sources))
