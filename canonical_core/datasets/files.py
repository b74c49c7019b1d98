"""Reading the files that capture layouts are made of besides their images (`images`): text,
matrices and intrinsics; finding a capture's frames and the files of each (`RGBDFile`). As in
`images`, a reader's ValueError names the file and the problem.

Example:
    >>> parse_floats(["1", "2.5"], "poses.txt").tolist()
    [1.0, 2.5]
"""

from __future__ import annotations

import argparse
import math
import re
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Sequence, TypeVar

import numpy as np
from ..calibration import validate_image_intrinsics, validate_intrinsics
from ..resample import depth_size_problem
from .distortion import undistort_image
from .images import check_depth_scale, image_size, read_depth, read_rgb

if TYPE_CHECKING:
    from ..camera import Camera
    from ..frame import Frame

def read_text(path: str | Path) -> str:
    """A text file's contents; ValueError naming the file when it is missing or not text."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: unreadable text file ({exc})") from None


def read_numbers(path: str | Path, count: int) -> np.ndarray:  # [count] float64
    """Read exactly ``count`` whitespace-separated numbers from a text file ('#' starts a comment)."""
    text = read_text(path)
    words = [w for line in text.splitlines() for w in line.split("#", 1)[0].split()]
    if len(words) != count:
        raise ValueError(f"{path}: expected {count} numbers, got {len(words)}")
    return parse_floats(words, str(path))


def parse_floats(words: Sequence[str], where: str) -> np.ndarray:  # [len(words)] float64
    """Words -> float64 array; ValueError naming ``where`` and the offending word."""
    try:
        return np.array([float(w) for w in words])
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def read_matrix(path: str | Path, rows: int, cols: int) -> np.ndarray:  # [rows, cols] float64
    """Read a rows x cols matrix written as text (one row a line, as tsdf-fusion and 7-Scenes do)."""
    return read_numbers(path, rows * cols).reshape(rows, cols)


def write_matrix(path: str | Path, matrix: np.ndarray) -> None:
    """Write a matrix as text, one row a line, with enough digits to re-read float64 exactly."""
    lines = (" ".join(f"{x:.17g}" for x in row) for row in np.asarray(matrix, dtype=np.float64))
    Path(path).write_text("\n".join(lines) + "\n")


def as_intrinsics(value, field: str = "intrinsics") -> np.ndarray:  # [3, 3] float64
    """A 3x3 K from a 3x3 array-like or a 4-vector (fx, fy, cx, cy), validated.

    Example:
        >>> as_intrinsics((585, 585, 320, 240)).tolist()
        [[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]]
    """
    array = np.asarray(value.detach().cpu() if hasattr(value, "detach") else value, dtype=np.float64)
    if array.shape == (4,):
        fx, fy, cx, cy = array
        array = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    elif array.shape != (3, 3):
        raise ValueError(f"{field}: expected a 3x3 matrix or (fx, fy, cx, cy), got shape {list(array.shape)}")
    return validate_intrinsics(array, field)


def find_one(folders: Sequence[Path], patterns: Sequence[str]) -> Path | None:
    """The first file matching ``patterns`` (in order) in ``folders`` (in order), or None.

    Raises ValueError when one pattern matches several files in a folder (which one is meant?).
    """
    for folder in folders:
        for pattern in patterns:
            hits = sorted(p for p in folder.glob(pattern) if p.is_file())
            if len(hits) > 1:
                raise ValueError(f"{folder}: several files match {pattern!r}: {[h.name for h in hits]}")
            if hits:
                return hits[0]
    return None


def read_intrinsics_file(path: Path) -> np.ndarray:  # [3, 3] float64
    """Read and validate a 3x3 intrinsics text file."""
    return validate_intrinsics(read_matrix(path, 3, 3), str(path))


def intrinsics_arg(text: str) -> tuple[float, float, float, float]:
    """``fx,fy,cx,cy`` (pixels) -> the four numbers, the focal lengths positive: the command lines'
    ``--K`` (an argparse type; its error names what was expected).

    Example:
        >>> intrinsics_arg("517.3,516.5,318.6,255.3")
        (517.3, 516.5, 318.6, 255.3)
    """
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(map(math.isfinite, values)) or min(values[:2]) <= 0:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy in pixels (four numbers, positive focal "
                                         f"lengths, e.g. 517.3,516.5,318.6,255.3), got {text!r}")
    return values


def depth_scale_arg(text: str) -> float:
    """Depth units per metre (`images.check_depth_scale`): the command lines' ``--depth-scale``.

    Example:
        >>> depth_scale_arg("1000")
        1000.0
    """
    try:
        return check_depth_scale(float(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("depth_scale: ")) from None


def add_capture_options(parser: argparse.ArgumentParser) -> None:
    """``--K`` and ``--depth-scale`` of a command that reads a capture: what its own files do not
    say, or say otherwise (`detect.load_dataset`'s ``K`` and ``depth_scale``)."""
    parser.add_argument("--K", type=intrinsics_arg, metavar="FX,FY,CX,CY",
                        help="the camera's intrinsics in pixels, for a capture without an intrinsics file (a TUM "
                             "capture's, e.g. 517.3,516.5,318.6,255.3 for freiburg1), or in place of its own")
    parser.add_argument("--depth-scale", type=depth_scale_arg, default=None, metavar="UNITS",
                        help="depth units per metre of the capture's depth images, where they are not its layout's "
                             "(e.g. 1000 for a TUM-layout capture written in millimetres; default: the layout's)")


class MissingFile(ValueError):
    """A file that a capture lists is not there; the message names it and where it is listed."""


class MissingIntrinsics(ValueError):
    """A capture holds no intrinsics file and none were given: its loader cannot place its pixels."""


class SkippedFrames(UserWarning):
    """A capture lists frames whose files are missing, and its loader left them out (``strict=False``)."""


Listed = TypeVar("Listed")
Resolved = TypeVar("Resolved")


def found_frames(listed: Iterable[Listed], resolve: Callable[[Listed], Resolved], listing: str | Path,
                 strict: bool) -> list[Resolved]:
    """``resolve`` of each frame a capture lists, without those whose files are missing (``resolve``
    raises `MissingFile` for them). With ``strict`` the first such frame's error is raised; otherwise
    they are skipped and one `SkippedFrames` warning counts them and names the first. ValueError when
    no listed frame is left.

    A capture copied in part (67 frames listed, 50 images there) then streams the frames it has, as
    a reconstruction tool reads what it finds; ``strict`` is for pipelines that must not lose one."""
    kept, missing, total = [], [], 0
    for item in listed:
        total += 1
        try:
            kept.append(resolve(item))
        except MissingFile as exc:
            if strict:
                raise
            missing.append(exc)
    if missing and not kept:
        raise ValueError(f"{listing}: none of its {total} listed frames has its files (the first: {missing[0]})")
    if missing:
        warnings.warn(f"{listing}: skipped {len(missing)} of {total} listed frames whose files are missing "
                      f"(the first: {missing[0]}); strict=True refuses such a capture", SkippedFrames, stacklevel=3)
    return kept


def select(items: Sequence, stride: int, max_frames: int | None) -> list:
    """Every ``stride``-th item, at most ``max_frames`` of them (input checks name the argument)."""
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride: expected a positive integer, got {stride!r}")
    if max_frames is not None and (
        isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1
    ):
        raise ValueError(f"max_frames: expected a positive integer or None, got {max_frames!r}")
    return list(items[::stride][:max_frames])


@dataclass(frozen=True, eq=False)
class RGBDFile:
    """One frame on disk, resolved and checked but not read: ``load()`` reads the images.

    Attributes:
        frame_id: the frame's identifier (file stem or timestamp).
        color: colour image path.
        depth: depth image path, or None for an RGB-only frame.
        K: [3, 3] float64 intrinsics; c2w: [4, 4] float64 camera-to-world, OpenCV axes.
        depth_scale: raw depth units per metre (metres = value / depth_scale).
        size: expected (width, height) when the layout states it, else taken from the image.
        distortion: OpenCV (k1, k2, p1, p2, k3) to undo on load, or None for a pinhole image.
    """

    frame_id: str
    color: Path
    depth: Path | None
    K: np.ndarray
    c2w: np.ndarray
    depth_scale: float = 1000.0
    size: tuple[int, int] | None = None
    distortion: tuple[float, ...] | None = None

    def load(self) -> Frame:
        # torch loads with the first frame read, not when a capture is listed (`sequence`)
        from ..camera import Camera
        from ..frame import Frame

        rgb = read_rgb(self.color)
        depth = None if self.depth is None else read_depth(self.depth, self.depth_scale)
        height, width = rgb.shape[:2]
        self._check_size(width, height)  # a colour image of another size than the capture's: named as such
        if depth is not None and depth.shape != (height, width):  # a lower resolution's registered depth?
            mismatch = (f"{self.depth}: depth size {depth.shape[1]}x{depth.shape[0]} does not match the colour image "
                        f"{self.color} ({width}x{height})")
            if self.distortion is not None:
                raise ValueError(f"{mismatch}; undistortion needs them at one size")
            problem = depth_size_problem((width, height), (depth.shape[1], depth.shape[0]))  # `Frame`'s own check
            if problem is not None:
                raise ValueError(f"{mismatch}: {problem.removeprefix('depth: ')}")
        if self.distortion is not None:
            rgb = undistort_image(rgb, self.K, self.distortion, mode="bilinear")
            if depth is not None:
                # nearest: interpolating across a depth edge would invent surfaces between objects
                depth = undistort_image(depth, self.K, self.distortion, mode="nearest")
        camera = Camera(self.K, self.c2w, width, height)
        # depth at a lower resolution: the frame is made at its pixels (`Frame`)
        return Frame(rgb=rgb, camera=camera, depth=depth, frame_id=self.frame_id)

    def view(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        """`FrameSource.view`: the colour camera, the camera `load` gives the frame (undistortion keeps K
        and the size), but for depth at a lower resolution, whose frames are made at its pixels."""
        width, height = image_size(self.color)
        self._check_size(width, height)
        validate_image_intrinsics(self.K, width, height)
        return self.K, self.c2w, width, height

    def _check_size(self, width: int, height: int) -> None:
        if self.size is not None and self.size != (width, height):
            raise ValueError(f"{self.color}: image is {width}x{height}, the capture's are {self.size[0]}x{self.size[1]} "
                             "(its layout's size, or its first frame's: intrinsics are for one image size)")


def one_size(sources: list[RGBDFile]) -> list[RGBDFile]:
    """``sources`` expecting the first one's image size where the layout states none: a capture's
    intrinsics are for one size, and a frame of another would be read with the wrong camera."""
    if not sources or sources[0].size is not None:
        return sources
    size = image_size(sources[0].color)
    return [replace(source, size=size) for source in sources]


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def natural_key(path: Path) -> list:
    """A file name's sort key with its numbers as numbers: frame numbers are usually zero-padded, but
    unpadded ones (``2.png`` before ``10.png``) keep their order too, as Open3D's own tools sort them."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def posed_images(images: Path, depth: Path, K: np.ndarray, poses: Sequence[np.ndarray], depth_scale: float,
                 stride: int, max_frames: int | None, pose_file: Path) -> list[RGBDFile]:
    """One `RGBDFile` per kept colour image of ``images`` (file-name order, `natural_key`), the k-th taking
    ``poses[k]`` and, where it exists, the depth image of the same stem (``.png``) in ``depth``
    (else the frame is RGB-only). Layouts whose poses are listed in image order share this."""
    check_depth_scale(depth_scale)
    files = sorted((p for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
    if len(poses) != len(files):
        raise ValueError(f"{pose_file}: {len(poses)} poses for {len(files)} images in {images} "
                         "(one per image, in file-name order, numbers as numbers)")
    out = []
    for k in select(range(len(files)), stride, max_frames):
        d = depth / (files[k].stem + ".png")
        out.append(RGBDFile(files[k].stem, files[k], d if d.is_file() else None, K, poses[k], depth_scale))
    # a depth folder that lacks some images' depth: a copy that lost files, more often than not (a
    # capture without one is colour-only by design)
    if (without := [f.frame_id for f in out if f.depth is None]) and depth.is_dir():
        warnings.warn(f"{depth}: {len(without)} of {len(out)} images have no depth image of their name (the first: "
                      f"{without[0]}); they fold as colour-only frames, their depth estimated", stacklevel=3)
    return out

