"""nerfstudio / instant-ngp ``transforms.json`` captures.

- ``frames[i].transform_matrix``: camera-to-world, OpenGL axes (x right, y up, z backward);
  converted to OpenCV axes with ``c2w_gl @ diag(1, -1, -1, 1)``.
- intrinsics ``fl_x fl_y cx cy w h`` at the top level or per frame (per frame wins); instant-ngp may
  give only ``camera_angle_x`` (and ``camera_angle_y``): fl = 0.5 w / tan(0.5 angle). Missing
  ``fl_y`` = ``fl_x``; missing ``cx, cy`` = image centre; missing ``w, h`` = the image's size.
- pixel convention: nerfstudio and instant-ngp cast the ray of pixel column i through i + 0.5
  (pixel edges on integers, as COLMAP), while our K puts pixel centres on integers (OpenCV), so
  ``cx = cx_json - 0.5`` and ``cy = cy_json - 0.5``.
- OpenCV distortion ``k1 k2 p1 p2`` (and ``k3``): images are undistorted on load into a pinhole
  image with the same K (colour bilinear, depth nearest-neighbour).
- optional ``depth_file_path`` per frame: 16-bit PNG, metres = value * depth_unit_scale_factor
  (nerfstudio's name; the argument, else a top-level key of that name, else 1/1000).
- ``camera_model`` other than OPENCV / PINHOLE / SIMPLE_PINHOLE (fisheye, equirectangular) is
  refused. instant-ngp's ``scale`` / ``offset`` / ``aabb_scale`` are its training-time
  normalisation, not part of the capture, and are ignored.
- a frame whose image (or depth) file is missing is left out, with one warning that counts such
  frames; ``strict=True`` refuses the capture instead.

Example:
    >>> seq = load_transforms_json("my_capture/transforms.json")  # doctest: +SKIP
    >>> seq[0].camera  # doctest: +SKIP
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..calibration import OPENGL_TO_OPENCV, validate_pose
from .files import MissingFile, RGBDFile, as_intrinsics, found_frames, read_text, select
from .images import DEPTH_SCALE_RANGE, image_size
from .sequence import FrameSequence

DEFAULT_DEPTH_UNIT_SCALE_FACTOR = 1e-3
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV order
CAMERA_KEYS = ("camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y") + DISTORTION_KEYS
SUPPORTED_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _number(params: dict, key: str, where: str) -> float:
    value = params[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _image_path(root: Path, value, where: str, key: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ValueError(f"{where}: {key} must be a non-empty string, got {value!r}")
    path = root / value
    if not path.is_file() and not path.suffix:  # instant-ngp's NeRF-synthetic scenes omit ".png"
        path = next((path.with_suffix(s) for s in _IMAGE_SUFFIXES if path.with_suffix(s).is_file()), path)
    if not path.is_file():
        raise MissingFile(f"{path}: file not found ({where}.{key})")
    return path


def camera_from_params(
    params: dict, color: Path, where: str
) -> tuple[np.ndarray, tuple[int, int], tuple[float, ...] | None]:  # K [3, 3], (w, h), distortion
    """Intrinsics, image size and OpenCV distortion (None when all zero) from transforms.json keys."""
    model = params.get("camera_model", "OPENCV")
    if model not in SUPPORTED_MODELS:
        raise ValueError(f"{where}: camera_model {model!r} is not supported (expected one of {SUPPORTED_MODELS})")
    if "w" in params and "h" in params:
        w, h = _number(params, "w", where), _number(params, "h", where)
        if w != int(w) or h != int(h) or w < 1 or h < 1:
            raise ValueError(f"{where}: w, h must be positive integers, got {params['w']!r}, {params['h']!r}")
        w, h = int(w), int(h)
    else:
        w, h = image_size(color)
    focal = {}
    for axis, size in (("x", w), ("y", h)):
        if f"fl_{axis}" in params:
            focal[axis] = _number(params, f"fl_{axis}", where)
        elif f"camera_angle_{axis}" in params:
            angle = _number(params, f"camera_angle_{axis}", where)
            if not 0 < angle < math.pi:
                raise ValueError(f"{where}: camera_angle_{axis} must be in (0, pi) radians, got {angle!r}")
            focal[axis] = 0.5 * size / math.tan(0.5 * angle)
    if "x" not in focal:
        raise ValueError(f"{where}: no focal length (fl_x or camera_angle_x)")
    cx = _number(params, "cx", where) if "cx" in params else w / 2
    cy = _number(params, "cy", where) if "cy" in params else h / 2
    K = as_intrinsics((focal["x"], focal.get("y", focal["x"]), cx - 0.5, cy - 0.5), where)
    distortion = tuple(_number(params, k, where) if k in params else 0.0 for k in DISTORTION_KEYS)
    return K, (w, h), (distortion if any(distortion) else None)


def _frame_params(defaults: dict, frame: dict) -> dict:
    """A frame's camera parameters: its own over the file's. A focal length it gives one way (``fl_x``
    or ``camera_angle_x``) replaces the file's given either way: a frame's own angle is not overruled
    by the file's focal length (which `camera_from_params` would read first)."""
    params = dict(defaults)
    for axis in ("x", "y"):
        if f"fl_{axis}" in frame or f"camera_angle_{axis}" in frame:
            params.pop(f"fl_{axis}", None)
            params.pop(f"camera_angle_{axis}", None)
    return params | {k: frame[k] for k in CAMERA_KEYS if k in frame}


def load_transforms_json(
    path: str | Path,
    depth_unit_scale_factor: float | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    strict: bool = False,
) -> FrameSequence:
    """Load a nerfstudio / instant-ngp capture as a lazily-read `FrameSequence`.

    Args:
        path: the ``transforms.json`` file or the folder holding it (image paths are relative to it).
        depth_unit_scale_factor: metres per raw depth unit; None = the file's top-level
            ``depth_unit_scale_factor`` if present, else 1/1000 (millimetres).
        stride, max_frames: keep every stride-th frame, at most max_frames of them (of the frames whose
            files are there).
        strict: refuse (ValueError) a file that lists a frame whose image or depth file is missing;
            by default such frames are left out, with one `SkippedFrames` warning that counts them.

    Returns frames with ``frame_id`` = the colour file's stem, undistorted when the file gives
    distortion coefficients, with depth when frames have ``depth_file_path``.

    Example:
        >>> seq = load_transforms_json("nerfstudio_capture", max_frames=10)  # doctest: +SKIP
    """
    json_path = Path(path)
    if json_path.is_dir():
        json_path = json_path / "transforms.json"
    try:
        meta = json.loads(read_text(json_path))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{json_path}: invalid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise ValueError(f"{json_path}: expected an object with a non-empty 'frames' list")
    factor = meta.get("depth_unit_scale_factor", DEFAULT_DEPTH_UNIT_SCALE_FACTOR)
    factor = factor if depth_unit_scale_factor is None else depth_unit_scale_factor
    low, high = DEPTH_SCALE_RANGE  # of units per metre: the factor is its inverse, metres per unit
    if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not 1.0 / high <= factor <= 1.0 / low:
        raise ValueError(f"depth_unit_scale_factor: expected metres per depth unit between {1.0 / high:g} and "
                         f"{1.0 / low:g} (e.g. 0.001 for millimetres), got {factor!r}")
    root = json_path.parent
    defaults = {k: meta[k] for k in CAMERA_KEYS if k in meta}

    def files(entry: tuple[int, object]) -> tuple[str, dict, Path, Path | None]:  # MissingFile if one is not there
        index, frame = entry
        where = f"{json_path}: frames[{index}]"
        if not isinstance(frame, dict):
            raise ValueError(f"{where}: expected an object, got {type(frame).__name__}")
        color = _image_path(root, frame.get("file_path"), where, "file_path")
        depth = _image_path(root, frame["depth_file_path"], where, "depth_file_path") if "depth_file_path" in frame else None
        return where, frame, color, depth

    # a frame's id is its image's name, or where two cameras' images share names (images/0001.png and
    # images_cam2/0001.png), its path in the capture: ids name one frame each
    stems = [Path(str(f.get("file_path", ""))).stem for f in meta["frames"] if isinstance(f, dict)]
    by_path = len(set(stems)) < len(stems)
    sources = []
    listed = found_frames(enumerate(meta["frames"]), files, json_path, strict)
    for where, frame, color, depth in select(listed, stride, max_frames):
        K, size, distortion = camera_from_params(_frame_params(defaults, frame), color, where)
        if "transform_matrix" not in frame:
            raise ValueError(f"{where}: no transform_matrix")
        try:
            c2w_gl = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}.transform_matrix: expected a 4x4 array of numbers") from None
        c2w = validate_pose(c2w_gl, f"{where}.transform_matrix") @ OPENGL_TO_OPENCV
        frame_id = os.path.relpath(color.with_suffix(""), root).replace(os.sep, "/") if by_path else color.stem
        sources.append(RGBDFile(frame_id, color, depth, K, c2w, 1.0 / factor, size, distortion))
    return FrameSequence(json_path.parent.name, sources)
