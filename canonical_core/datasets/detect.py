"""Detect a capture's layout from the files it holds, and load it with the matching loader.

Example:
    >>> seq = load_dataset("../shared/data/slambook_rgbd5", K=(518.0, 519.0, 325.5, 253.5))  # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from .deep_video_mvs import is_deep_video_mvs, load_deep_video_mvs
from .images import check_depth_scale
from .label_fusion import has_label_maps, load_label_fusion
from .redwood import is_redwood, load_redwood
from .sequence import FrameSequence
from .transforms_json import load_transforms_json
from .tsdf_fusion import find_frames_folder, load_tsdf_fusion
from .tum import load_tum

Layout = Literal["transforms_json", "tum", "tsdf_fusion", "deep_video_mvs", "redwood", "label_fusion"]


class UnknownLayout(ValueError):
    """A path that holds no capture a loader reads (nothing of any layout there)."""


def detect_layout(path: str | Path) -> Layout:
    """Which loader reads ``path``: a transforms.json (file or in the folder) -> "transforms_json";
    groundtruth.txt, or pose.txt with a color/ folder -> "tum"; K.txt, poses.txt and images/ ->
    "deep_video_mvs"; trajectory.log and image/ -> "redwood"; frame-*.pose.txt (in the folder or one
    subfolder) -> "label_fusion" with frame-*.segm.png or .mask.png label maps beside them, else
    "tsdf_fusion". Raises `UnknownLayout` (a ValueError) naming the path when nothing matches."""
    path = Path(path)
    if path.is_file() and path.suffix == ".json":
        return "transforms_json"
    if not path.is_dir():
        raise UnknownLayout(f"{path}: not a folder or a transforms.json file")
    if (path / "transforms.json").is_file():
        return "transforms_json"
    if (path / "groundtruth.txt").is_file() or ((path / "pose.txt").is_file() and (path / "color").is_dir()):
        return "tum"
    if is_deep_video_mvs(path):
        return "deep_video_mvs"
    if is_redwood(path):
        return "redwood"
    folder = find_frames_folder(path)
    if folder is not None:
        return "label_fusion" if has_label_maps(folder) else "tsdf_fusion"
    raise UnknownLayout(
        f"{path}: no known capture layout (looked for transforms.json; groundtruth.txt or pose.txt + color/; "
        "K.txt + poses.txt + images/; trajectory.log + image/; frame-*.pose.txt)"
    )


_LOADERS = {"transforms_json": load_transforms_json, "tum": load_tum, "tsdf_fusion": load_tsdf_fusion,
            "deep_video_mvs": load_deep_video_mvs, "redwood": load_redwood, "label_fusion": load_label_fusion}


# the layouts that list their frames (in a file, or as pose files) and so may list some whose images
# are missing; the others' frames are the image folder's own files
_LISTING = {"transforms_json", "tum", "tsdf_fusion", "label_fusion"}
# the layouts whose depth images' units are the layout's (their loaders' ``depth_scale``)
_DEPTH_SCALED = {"tum", "tsdf_fusion", "deep_video_mvs", "redwood"}
# the layouts whose intrinsics come from a file (or their loader's default), by their loader's argument
_INTRINSICS = {"tum": "K", "tsdf_fusion": "intrinsics", "label_fusion": "intrinsics", "redwood": "intrinsics"}


def load_dataset(path: str | Path, strict: bool = False, K=None, depth_scale: float | None = None,
                 **kwargs) -> FrameSequence:
    """Load any supported capture: detects the layout (`detect_layout`) and passes ``kwargs`` on
    (e.g. ``stride=`` / ``max_frames=`` for all).

    ``depth_scale`` (raw depth units per metre: 1000 for millimetres, 5000 for TUM's own) replaces the
    layout's for the layouts whose depth images carry no scale of their own (TUM, tsdf-fusion / 7-Scenes,
    deep-video-mvs, Redwood): a capture written in other units than its layout's. A ValueError for
    the others (transforms.json states its own; label-fusion's code is fixed).

    ``K`` (a 3x3 matrix or (fx, fy, cx, cy), pixels) gives the camera's intrinsics to the layouts
    that read them from a file (TUM, tsdf-fusion / 7-Scenes, label-fusion, Redwood): for a capture
    without one (its loader raises `MissingIntrinsics`), or in place of its own. A ValueError for the
    layouts whose frames carry their own (transforms.json, deep-video-mvs).

    A frame the capture lists whose image files are missing is left out, with one `SkippedFrames`
    warning that counts such frames; with ``strict`` it is a ValueError naming the file.

    Example:
        >>> seq = load_dataset("../shared/data/realsense_shelf", max_frames=4)  # doctest: +SKIP
        >>> len(seq)  # doctest: +SKIP
        4
    """
    layout = detect_layout(path)
    if layout in _LISTING:
        kwargs["strict"] = strict
    if K is not None:
        if layout not in _INTRINSICS:
            raise ValueError(f"K: a {layout} capture's frames carry their own intrinsics; give none")
        kwargs[_INTRINSICS[layout]] = K
    if depth_scale is not None:
        if layout not in _DEPTH_SCALED:
            raise ValueError(f"depth_scale: a {layout} capture's depth carries its own scale; give none")
        kwargs["depth_scale"] = check_depth_scale(depth_scale)
    return _LOADERS[layout](path, **kwargs)
