"""label-fusion's bins: the tsdf-fusion frame layout with its own depth code and per-frame label maps.

- ``frame-NNNNNN.color.png``: 8-bit RGB; ``frame-NNNNNN.pose.txt``: 4x4 camera-to-world, OpenCV axes;
  ``camera-intrinsics.color.txt`` (or any tsdf-fusion intrinsics file) at the folder root;
- ``frame-NNNNNN.depth.png``: uint16 in tenths of a millimetre, bit-rotated: the value v holds
  d = ((v >> 3) | (v << 13)) & 0xFFFF (in 32 bits), metres = d / 10000; 0 = missing (or, a
  tsdf-fusion capture with label maps added, millimetres: told apart by `rotated_depth_code`);
- ``frame-NNNNNN.segm.png`` (uint8 label id per pixel, 0 = background) or ``frame-NNNNNN.mask.png``
  (0 or 255): read as a class map (`Frame.labels`, fused as one-hot label scores), one class per id
  found in the capture's label maps, so that fused scenes carry them (segmentation views).

Example:
    >>> seq = load_label_fusion("../shared/data/apc_bins/bin_labels")  # doctest: +SKIP
    >>> seq.label_ids, seq[0].labels.shape, seq[0].num_classes  # doctest: +SKIP
    ((0, 48, 132), torch.Size([480, 640]), 3)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from ..calibration import validate_image_intrinsics, validate_pose
from .files import (MissingIntrinsics, as_intrinsics, find_one, found_frames, natural_key, read_intrinsics_file,
                    read_matrix, select)
from .images import depth_from_uint16, image_size, read_depth, read_rgb
from .sequence import FrameSequence
from .tsdf_fusion import INTRINSICS_PATTERNS, POSE_PATTERN, find_frames_folder, pose_frame_files

if TYPE_CHECKING:
    from ..camera import Camera
    from ..frame import Frame

LABEL_SUFFIXES = (".segm.png", ".mask.png")
DEPTH_UNITS_PER_METRE = 10000.0
TSDF_FUSION_UNITS_PER_METRE = 1000.0  # millimetres, the tsdf-fusion layout's depth


def has_label_maps(folder: Path) -> bool:
    return any(any(folder.glob("frame-*" + suffix)) for suffix in LABEL_SUFFIXES)


def unrotate_depth(raw: np.ndarray) -> np.ndarray:  # [H, W] uint16 as stored -> [H, W] uint16 tenths of a mm
    """Undo label-fusion's bit rotation of its depth images: d = ((v >> 3) | (v << 13)) & 0xFFFF.

    Example:
        >>> unrotate_depth(np.array([[0, 8, 1]], np.uint16)).tolist()
        [[0, 1, 8192]]
    """
    v = raw.astype(np.uint32)
    return (((v >> 3) | (v << 13)) & 0xFFFF).astype(np.uint16)


def rotated_depth_code(raw: np.ndarray) -> bool:  # [H, W] uint16 as stored
    """Whether a depth image is in label-fusion's code (bit-rotated tenths of a millimetre) rather than
    tsdf-fusion's millimetres, by which decoding is a surface: the wrong one scatters neighbouring
    pixels by multiples of 0.8 m (a stored value's low bits, which differ from pixel to pixel on any
    measured surface, become the depth's high ones). A tsdf-fusion capture with label maps beside its
    frames is read in millimetres so.

    Example:
        >>> plane = 600 + np.random.default_rng(0).integers(-2, 3, (8, 64))  # millimetres, a sensor's noise
        >>> rotated_depth_code(plane.astype(np.uint16))
        False
        >>> rotated_depth_code(((plane * 10 << 3) | (plane * 10 >> 13)).astype(np.uint16))  # label-fusion's
        True
    """
    return _roughness(depth_from_uint16(unrotate_depth(raw), DEPTH_UNITS_PER_METRE)) < _roughness(
        depth_from_uint16(raw, TSDF_FUSION_UNITS_PER_METRE))


def _roughness(depth: np.ndarray) -> float:
    """The median jump in metres between horizontal neighbours with depth (inf: none)."""
    left, right = depth[:, :-1], depth[:, 1:]
    both = (left > 0) & (right > 0)
    return float(np.median(np.abs(left[both] - right[both]))) if both.any() else float("inf")


def read_label_map(path: Path) -> np.ndarray:  # [H, W] uint8 label ids
    with Image.open(path) as image:
        if image.mode not in ("L", "P", "1"):
            raise ValueError(f"{path}: expected an 8-bit single-channel label map, got PIL mode {image.mode!r}")
        return np.asarray(image.convert("L"))


@dataclass(frozen=True, eq=False)
class LabelledFrameFile:
    """One label-fusion frame on disk; ``load()`` reads and decodes it."""

    frame_id: str
    color: Path
    depth: Path
    labels: Path | None
    K: np.ndarray  # [3, 3] float64
    c2w: np.ndarray  # [4, 4] float64
    label_ids: tuple[int, ...]  # the capture's ids, one label channel each
    rotated: bool = True  # label-fusion's depth code, else tsdf-fusion's millimetres (`rotated_depth_code`)

    def load(self) -> Frame:
        # torch loads with the first frame read, not when a capture is listed (`sequence`)
        from ..camera import Camera
        from ..frame import Frame

        rgb = read_rgb(self.color)
        stored = read_depth(self.depth, 1.0).astype(np.uint16)  # the raw values (0 and 65535 read as 0)
        depth = (depth_from_uint16(unrotate_depth(stored), DEPTH_UNITS_PER_METRE) if self.rotated
                 else depth_from_uint16(stored, TSDF_FUSION_UNITS_PER_METRE))
        labels = None
        if self.labels is not None:
            ids = read_label_map(self.labels)
            if ids.shape != depth.shape:
                raise ValueError(f"{self.labels}: label map {ids.shape[1]}x{ids.shape[0]} does not match the depth "
                                 f"image {self.depth} ({depth.shape[1]}x{depth.shape[0]})")
            channel = np.full(256, -1, np.int16)  # the capture's id -> its label channel
            channel[list(self.label_ids)] = np.arange(len(self.label_ids))
            labels = channel[ids]
        camera = Camera(self.K, self.c2w, rgb.shape[1], rgb.shape[0])
        return Frame(rgb=rgb, camera=camera, depth=depth, labels=labels, frame_id=self.frame_id,
                     num_classes=len(self.label_ids) if labels is not None else None)

    def view(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        """`FrameSource.view`: the camera `load` gives the frame."""
        width, height = image_size(self.color)
        validate_image_intrinsics(self.K, width, height)
        return self.K, self.c2w, width, height


class LabelledSequence(FrameSequence):
    """A `FrameSequence` that also names its label channels (``label_ids[c]`` is channel c's id)."""

    def __init__(self, name: str, sources, label_ids: tuple[int, ...]):
        super().__init__(name, sources)
        self.label_ids = label_ids


def load_label_fusion(
    path: str | Path,
    intrinsics=None,
    stride: int = 1,
    max_frames: int | None = None,
    strict: bool = False,
) -> LabelledSequence:
    """Load a label-fusion bin folder as a lazily-read sequence of frames with depth and labels.

    Args:
        path: the capture folder (frames in it or in one subfolder; intrinsics file at its root).
        intrinsics: 3x3 K or (fx, fy, cx, cy) in pixels; overrides the intrinsics file.
        stride, max_frames: keep every stride-th frame, at most max_frames of them.
        strict: refuse (ValueError) a pose file whose colour or depth image is missing; by default
            such frames are left out, with one `SkippedFrames` warning that counts them.

    The label channels are the ids found in all of the capture's label maps (read once, here), so
    every frame of it has the same channels whatever ``stride`` keeps.
    """
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"{root}: not a folder")
    folder = find_frames_folder(root)
    if folder is None or not has_label_maps(folder):
        raise ValueError(f"{root}: not a label-fusion folder (expected {POSE_PATTERN} with "
                         f"{' or '.join('frame-*' + s for s in LABEL_SUFFIXES)})")
    patterns = ("camera-intrinsics.color.txt", *INTRINSICS_PATTERNS)
    found = None if intrinsics is not None else find_one(list(dict.fromkeys([root, folder])), patterns)
    if intrinsics is None and found is None:
        raise MissingIntrinsics(f"{root}: no intrinsics file ({', '.join(patterns)}); pass intrinsics=(fx, fy, cx, cy)")
    K = as_intrinsics(intrinsics) if intrinsics is not None else read_intrinsics_file(found)
    poses = sorted(folder.glob(POSE_PATTERN), key=natural_key)
    label_files = {}
    for pose in poses:
        stem = pose.name[: -len(".pose.txt")]
        label_files[stem] = next((folder / (stem + s) for s in LABEL_SUFFIXES if (folder / (stem + s)).is_file()), None)
    ids = sorted(set().union(*(np.unique(read_label_map(p)).tolist() for p in label_files.values() if p is not None)))
    sources, rotated = [], None
    for stem, pose, color, depth in select(found_frames(poses, pose_frame_files, folder, strict), stride, max_frames):
        c2w = validate_pose(read_matrix(pose, 4, 4), str(pose))
        if rotated is None:  # the capture's depth code, from its first depth image
            rotated = rotated_depth_code(read_depth(depth, 1.0).astype(np.uint16))
        sources.append(LabelledFrameFile(stem, color, depth, label_files[stem], K, c2w, tuple(ids), rotated))
    return LabelledSequence(root.name, sources, tuple(ids))
