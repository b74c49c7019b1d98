"""The deep-video-mvs layout: ``K.txt``, ``poses.txt``, ``images/*.png``, ``depth/*.png``.

- ``K.txt``: the 3x3 pinhole matrix (pixels), images already undistorted;
- ``poses.txt``: one line per image, in sorted file-name order: the 16 numbers of a 4x4
  camera-to-world matrix, row-major, OpenCV axes, metres;
- ``images/NNNNN.png``: 8-bit RGB; ``depth/NNNNN.png``: uint16 in 1/depth_scale metres
  (millimetres by default), 0 = missing. A missing depth file makes that frame RGB-only.

Example:
    >>> seq = load_deep_video_mvs("../shared/data/hololens_office", stride=10)  # doctest: +SKIP
    >>> seq.frame_ids[:2]  # doctest: +SKIP
    ['00003', '00023']
"""

from __future__ import annotations

from pathlib import Path

from ..calibration import validate_pose
from .files import one_size, parse_floats, posed_images, read_intrinsics_file, read_text
from .sequence import FrameSequence


def is_deep_video_mvs(root: Path) -> bool:
    return (root / "K.txt").is_file() and (root / "poses.txt").is_file() and (root / "images").is_dir()


def load_deep_video_mvs(
    path: str | Path,
    depth_scale: float = 1000.0,
    stride: int = 1,
    max_frames: int | None = None,
) -> FrameSequence:
    """Load a deep-video-mvs folder as a lazily-read `FrameSequence`.

    Args:
        path: the capture folder (``K.txt``, ``poses.txt``, ``images/``, optional ``depth/``).
        depth_scale: raw depth units per metre (1000 for millimetres).
        stride, max_frames: keep every stride-th frame, at most max_frames of them.

    Returns frames with ``frame_id`` = the image's file stem, in file-name order.
    """
    root = Path(path)
    if not is_deep_video_mvs(root):
        raise ValueError(f"{root}: not a deep-video-mvs folder (expected K.txt, poses.txt and images/)")
    poses = []
    for k, line in enumerate(line.split() for line in read_text(root / "poses.txt").splitlines() if line.strip()):
        where = f"{root / 'poses.txt'}:{k + 1}"
        if len(line) != 16:
            raise ValueError(f"{where}: expected the 16 numbers of a 4x4 matrix, got {len(line)}")
        poses.append(validate_pose(parse_floats(line, where).reshape(4, 4), where))
    sources = posed_images(root / "images", root / "depth", read_intrinsics_file(root / "K.txt"), poses, depth_scale,
                           stride, max_frames, root / "poses.txt")
    return FrameSequence(root.name, one_size(sources))
