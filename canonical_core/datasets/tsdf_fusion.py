"""The tsdf-fusion / 7-Scenes layout: ``frame-NNNNNN.{color.png|color.jpg, depth.png, pose.txt}``.

- colour: 8-bit RGB; depth: uint16 in 1/depth_scale metres (mm by default), 0 (and 65535, the
  7-Scenes invalid code) = missing; pose: 4x4 camera-to-world text, OpenCV axes.
- intrinsics: a 3x3 text file at the folder root (``camera-intrinsics.txt``, ``intrinsics.K.txt``
  or ``*.K.txt``). 7-Scenes has none (fx = fy = 585, cx = 320, cy = 240): pass ``intrinsics=``.
- frames sit in the folder itself or in one subfolder (``frames/``, tsdf-fusion's ``rgbd-frames/``).
- a pose file whose colour or depth image is missing is left out, with one warning that counts
  such frames; ``strict=True`` refuses the capture instead.

Note that 7-Scenes depth comes from a separate, uncalibrated depth camera, so its depth is only
roughly registered to the colour image.

Example:
    >>> import tempfile
    >>> from canonical_core.datasets import synthetic_rgbd
    >>> folder = write_tsdf_fusion(synthetic_rgbd(num_frames=2, width=64, height=48), tempfile.mkdtemp())
    >>> seq = load_tsdf_fusion(folder)
    >>> seq.frame_ids, seq[0].depth.shape
    (['frame-000000', 'frame-000001'], torch.Size([48, 64]))
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from ..calibration import validate_pose
from .files import (MissingFile, MissingIntrinsics, RGBDFile, as_intrinsics, find_one, found_frames, natural_key,
                    one_size, read_intrinsics_file, read_matrix, select, write_matrix)
from .images import check_depth_scale, write_depth, write_rgb
from .sequence import FrameSequence

if TYPE_CHECKING:
    from ..frame import Frame

POSE_PATTERN = "frame-*.pose.txt"
INTRINSICS_PATTERNS = ("camera-intrinsics.txt", "intrinsics.K.txt", "*.K.txt")
_COLOR_SUFFIXES = (".color.png", ".color.jpg")


def find_frames_folder(root: Path) -> Path | None:
    """``root`` if it holds ``frame-*.pose.txt`` files, else its single subfolder that does."""
    if any(root.glob(POSE_PATTERN)):
        return root
    subfolders = sorted(d for d in root.iterdir() if d.is_dir() and any(d.glob(POSE_PATTERN)))
    if len(subfolders) > 1:
        raise ValueError(f"{root}: several subfolders hold frames ({[d.name for d in subfolders]}); pass one of them")
    return subfolders[0] if subfolders else None


def pose_frame_files(pose_path: Path) -> tuple[str, Path, Path, Path]:
    """(frame stem, pose file, colour image, depth image) of a ``frame-N.pose.txt``; `MissingFile`
    when an image is not there."""
    folder, stem = pose_path.parent, pose_path.name[: -len(".pose.txt")]
    colors = [folder / (stem + s) for s in _COLOR_SUFFIXES if (folder / (stem + s)).is_file()]
    if not colors:
        raise MissingFile(f"{folder / (stem + _COLOR_SUFFIXES[0])}: file not found (colour image for {pose_path.name})")
    depth = folder / f"{stem}.depth.png"
    if not depth.is_file():
        raise MissingFile(f"{depth}: file not found (depth image for {pose_path.name})")
    return stem, pose_path, colors[0], depth


def load_tsdf_fusion(
    path: str | Path,
    intrinsics=None,
    depth_scale: float = 1000.0,
    stride: int = 1,
    max_frames: int | None = None,
    strict: bool = False,
) -> FrameSequence:
    """Load a tsdf-fusion / 7-Scenes folder as a lazily-read `FrameSequence`.

    Args:
        path: the capture folder (frames in it or in one subfolder; intrinsics file at its root).
        intrinsics: 3x3 K or (fx, fy, cx, cy) in pixels; overrides any intrinsics file.
        depth_scale: raw depth units per metre (1000 for millimetres).
        stride, max_frames: keep every stride-th frame, at most max_frames of them.
        strict: refuse (ValueError) a pose file whose colour or depth image is missing; by default
            such frames are left out, with one `SkippedFrames` warning that counts them.

    Returns frames with ``frame_id`` = file stem (``frame-000015``), in frame-number order.

    Example:
        >>> seq = load_tsdf_fusion("../shared/data/realsense_shelf", stride=10)  # doctest: +SKIP
        >>> seq[0].camera.fx  # doctest: +SKIP
        615.195...
    """
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder")
    check_depth_scale(depth_scale)  # now, not at the first frame read
    folder = find_frames_folder(root)
    if folder is None:
        raise ValueError(f"{root}: no {POSE_PATTERN} files (tsdf-fusion / 7-Scenes layout) in it or its subfolders")
    if intrinsics is not None:
        K = as_intrinsics(intrinsics)
    else:
        found = find_one(list(dict.fromkeys([root, folder])), INTRINSICS_PATTERNS)
        if found is None:
            raise MissingIntrinsics(
                f"{root}: no intrinsics file ({', '.join(INTRINSICS_PATTERNS)}); pass intrinsics=(fx, fy, cx, cy), "
                "e.g. (585, 585, 320, 240) for 7-Scenes"
            )
        K = read_intrinsics_file(found)
    sources = []
    listed = found_frames(sorted(folder.glob(POSE_PATTERN), key=natural_key), pose_frame_files, folder, strict)
    for stem, pose_path, color, depth in select(listed, stride, max_frames):
        c2w = validate_pose(read_matrix(pose_path, 4, 4), str(pose_path))
        sources.append(RGBDFile(stem, color, depth, K, c2w, depth_scale))
    return FrameSequence(root.name, one_size(sources))


def write_tsdf_fusion(frames: Iterable[Frame], path: str | Path, depth_scale: float = 1000.0) -> Path:
    """Write RGB-D frames in the tsdf-fusion layout, readable by `load_tsdf_fusion`.

    Writes ``frame-NNNNNN.color.png``, ``.depth.png`` (uint16, round(metres * depth_scale)),
    ``.pose.txt`` (camera-to-world, full float64 precision) and one ``camera-intrinsics.txt``
    into ``path`` (created if needed). All frames must have depth and share one K. Refuses a
    folder that already holds frames, so two captures never mix. Returns the folder.

    Example:
        >>> import tempfile
        >>> from canonical_core.datasets import synthetic_rgbd
        >>> write_tsdf_fusion(synthetic_rgbd(num_frames=1, width=32, height=24), tempfile.mkdtemp()).is_dir()
        True
    """
    from ..frame import Frame  # torch: only a writer of frames needs it (`sequence`)

    folder = Path(path)
    if not depth_scale > 0:
        raise ValueError(f"depth_scale: expected a positive number, got {depth_scale!r}")
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    if folder.is_dir() and any(folder.glob("frame-*")):
        raise ValueError(f"{folder}: already holds frame-* files; write into an empty folder")
    folder.mkdir(parents=True, exist_ok=True)
    K = None
    for i, frame in enumerate(frames):
        if not isinstance(frame, Frame):
            raise ValueError(f"frames[{i}]: expected a Frame, got {type(frame).__name__}")
        if frame.depth is None:
            raise ValueError(f"frames[{i}] ({frame.frame_id!r}): has no depth; the tsdf-fusion layout stores RGB-D frames")
        if K is None:
            K = frame.camera.K64()
            write_matrix(folder / "camera-intrinsics.txt", K)
        elif not (frame.camera.K64() == K).all():
            raise ValueError(f"frames[{i}] ({frame.frame_id!r}): K {frame.camera.K64().tolist()} differs from frame 0's {K.tolist()}")
        stem = folder / f"frame-{i:06d}"
        write_rgb(f"{stem}.color.png", frame.rgb.numpy())
        write_depth(f"{stem}.depth.png", frame.depth.numpy(), depth_scale)
        write_matrix(f"{stem}.pose.txt", frame.camera.c2w64())
    if K is None:
        raise ValueError("frames: empty; nothing to write")
    return folder
