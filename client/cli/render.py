"""``render`` (views of a session at --frame-like cameras, a pose or a trajectory, to PNGs or .npy:
colour, depth, labels or features) and
``export`` (its Gaussians as .ply or .splat, or its surface mesh)."""

from __future__ import annotations

import argparse
import functools
import io
import os
import re
import sys
from pathlib import Path

import numpy as np

from canonical_core.datasets.files import intrinsics_arg  # the same --K as stream's (imports no torch, no numba)
from canonical_core.datasets.images import DEPTH_INVALID_CODE
from canonical_wire import NO_LABEL

from .common import (UsageError, add_connection, colour_arg, connect, seconds_arg, session_id, warnings_on_stderr,
                     writing)
from .poses import pose_text, read_pose_file


# -- render -------------------------------------------------------------------------------------
def add_render(p: argparse.ArgumentParser) -> None:
    add_connection(p)
    p.add_argument("--session", type=session_id, required=True)
    p.add_argument("--frame-like", metavar="DATASET:INDEX", action="append", default=[],
                   help="a view at the camera of frame INDEX of DATASET; repeatable, one view each. With --pose or "
                        "--trajectory, only its intrinsics and image size are taken")
    poses = p.add_mutually_exclusive_group()
    poses.add_argument("--pose", metavar="FILE", help="camera-to-world pose (OpenCV axes): a 4x4 matrix, or pose lines "
                                                      "as --trajectory reads them; needs --K and --size, or --frame-like")
    poses.add_argument("--trajectory", metavar="FILE",
                       help="one view per line: TUM 'timestamp tx ty tz qx qy qz qw' (camera-to-world, quaternion "
                            "scalar last; the timestamp optional) or the 16 numbers of a 4x4 matrix; '#' comments. "
                            "Needs --K and --size, or --frame-like")
    p.add_argument("--K", type=intrinsics_arg, metavar="FX,FY,CX,CY",
                   help="intrinsics in pixels: the views' with --pose or --trajectory, and the --frame-like "
                        "capture's (as `canonical stream --K`: for a capture without its own)")
    p.add_argument("--size", type=image_size_arg, metavar="WxH", help="image size (with --K), e.g. 640x480")
    p.add_argument("--width", type=int, help="image width (or --size)")
    p.add_argument("--height", type=int, help="image height (or --size)")
    p.add_argument("--max-gaussians", type=int, default=None)
    p.add_argument("--background", type=colour_arg, default=None, help="r,g,b in [0, 1]")
    p.add_argument("--colour", choices=["normalised", "composited"], default=None,
                   help="normalised (the service's default: each drawn pixel the surface's expected colour, not darkened "
                        "where splats cover it only in part) or composited (the blend over the background)")
    p.add_argument("--map", choices=MAPS, default="rgb",
                   help="what to write: rgb (colour), depth (a 16-bit PNG in units of --depth-scale, 0 where nothing "
                        "is drawn), labels (the fused labels' classes: a palette PNG, index 0 nothing drawn, k + 1 "
                        "class k) or features (a PCA picture of the feature map). With -o FILE.npy, the map's own "
                        "values instead: rgb uint8 [H,W,3], depth float32 metres, labels int16 [H,W] (-1 nothing "
                        "drawn), features float16 [H,W,C]")
    p.add_argument("--depth-scale", type=float, default=1000.0,
                   help="--map depth as PNG: units per metre (1000: millimetres, as most depth cameras store them; "
                        "TUM's captures use 5000)")
    add_wait_solved(p, "renders")
    p.add_argument("-o", "--output", required=True,
                   help="the PNG (or .npy: --map) to write; for several views a pattern with {i}, the view's index (e.g. "
                        "'views/{i:03d}.png'), or a folder (DIR/: view_0000.png, ...). The paths written are printed")


MAPS = ("rgb", "depth", "labels", "features")


def add_wait_solved(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--wait-solved", type=seconds_arg, default=120.0, metavar="SECONDS",
                   help=f"wait up to SECONDS for the colours of a session whose stream has paused to be solved (the "
                        f"service solves them in the background; {what} before then show the fused colours); 0: at once. "
                        "A session that is still taking frames is not waited for (default: 120)")


def wait_solved(session, seconds: float) -> None:
    """Wait up to ``seconds`` for ``session``'s solved colours (`Session.wait_for_colours`), saying
    on stderr that it waits, and how it ended."""
    if seconds == 0:
        return
    waited = []

    def progress(stats):
        if not waited:
            print(f"waiting for the colours of {stats['frames']} frames to be solved (--wait-solved 0: not to wait)",
                  file=sys.stderr, flush=True)
        waited.append(stats)

    stats = session.wait_for_colours(seconds, progress=progress)
    if not waited:
        return
    if stats["colours_solved_frames"] == stats["frames"]:
        note = "colours solved"
    elif stats["frames"] != waited[0]["frames"]:
        note = "the session is taking frames: its colours as they are (solved once its stream pauses)"
    else:
        note = f"colours not solved within {seconds:g} s: its colours as they are"
    print(note, file=sys.stderr, flush=True)


def image_size_arg(text: str) -> tuple[int, int]:
    """``WxH`` -> (W, H), both positive.

    Example:
        >>> image_size_arg("640x480")
        (640, 480)
    """
    width, sep, height = text.lower().partition("x")
    if not (sep and width.isdigit() and height.isdigit() and int(width) > 0 and int(height) > 0):
        raise argparse.ArgumentTypeError(f"expected WxH in pixels (e.g. 640x480), got {text!r}")
    return int(width), int(height)


@functools.lru_cache(maxsize=None)
def _capture(path: str, K: tuple | None = None):
    """A capture read once however many --frame-like views name it; ``K``: its intrinsics where it has
    none (--K), a usage error naming --K when it needs them."""
    from canonical_core.datasets import MissingIntrinsics, load_dataset

    try:
        return load_dataset(path, K=K)
    except MissingIntrinsics as exc:
        raise UsageError(f"--frame-like: {exc} (here: --K fx,fy,cx,cy)") from None


def view_poses(path: str, option: str) -> list[np.ndarray]:
    """The camera-to-world poses of a --pose or --trajectory file (``option``), in file order: one 4x4
    (or 3x4) matrix written over its lines, else one pose a line (`read_pose_file`). ValueError naming
    ``option`` and the file for a file without a pose (only comments, empty) or one that cannot be read."""
    from canonical_core.calibration import validate_pose

    try:
        text = pose_text(path)
        if not any(line.split("#", 1)[0].strip() for line in text.splitlines()):
            raise ValueError(f"no poses in {path}")
        try:
            matrix = np.loadtxt(io.StringIO(text), dtype=np.float64, ndmin=2)
        except ValueError:  # not one block of numbers: pose lines with keys, or malformed (read_pose_file says where)
            matrix = None
        if matrix is not None and matrix.shape in ((4, 4), (3, 4)):
            return [validate_pose(matrix, str(path))]
        return list(read_pose_file(path, text).values())
    except ValueError as exc:
        raise ValueError(f"{option}: {exc}") from None


def render_views(args) -> list[tuple[np.ndarray, np.ndarray, int, int]]:
    """(K, c2w, width, height) of each view the arguments name, in order: each --frame-like's camera,
    or each pose of --pose / --trajectory with --K and --size (else the --frame-like camera's)."""
    pose_file = args.pose or args.trajectory
    if pose_file is None and (args.size or args.width or args.height):
        raise UsageError("--size goes with --pose or --trajectory (--frame-like brings its own)")
    # --K: the views' intrinsics, and those of a --frame-like capture that has none
    cameras = [frame_like_camera(spec, tuple(args.K) if args.K else None) for spec in args.frame_like]
    if pose_file is None:
        return cameras
    width, height = args.size or (args.width, args.height)
    if args.K:
        fx, fy, cx, cy = args.K
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        if not (width and height):
            if len(cameras) != 1:
                raise UsageError("--K needs --size WxH (or one --frame-like whose image size to take)")
            width, height = cameras[0][2:]
    elif len(cameras) == 1:
        K, _, own_width, own_height = cameras[0]
        width, height = width or own_width, height or own_height
    else:
        raise UsageError("--pose and --trajectory need --K fx,fy,cx,cy and --size WxH, or one --frame-like "
                         "DATASET:INDEX whose intrinsics and image size to take")
    return [(K, c2w, width, height) for c2w in view_poses(pose_file, "--pose" if args.pose else "--trajectory")]


def output_paths(output: str, count: int) -> list[Path]:
    """Where each of ``count`` views goes: ``output`` with its {i} filled in, or in the folder
    ``output`` (view_0000.png, ...), or, for one view, ``output`` itself."""
    if "{" in output:
        try:
            paths = [Path(output.format(i=i)) for i in range(count)]
        except (KeyError, IndexError, ValueError) as exc:
            raise UsageError(f"-o: expected a pattern with {{i}} (e.g. view_{{i:03d}}.png), got {output!r} ({exc!r})") from None
        if len(set(paths)) < count:
            raise UsageError(f"-o: {output!r} names one file for several views; put {{i}} in it")
        return paths
    if output.endswith(("/", os.sep)) or Path(output).is_dir():
        return [Path(output) / f"view_{i:04d}.png" for i in range(count)]
    if count > 1:
        raise UsageError(f"-o: {count} views need a pattern with {{i}} (e.g. view_{{i:03d}}.png) or a folder, got {output!r}")
    return [Path(output)]


def frame_like_camera(spec: str, K: tuple | None = None) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The camera of ``--frame-like DATASET:INDEX`` as (K, c2w, width, height), read without decoding
    the frame (`FrameSource.view`; ``K``: the capture's intrinsics where it has none): UsageError for a
    spec without an index or an index the dataset does not have, or a capture that needs ``K``,
    ValueError naming the option for a dataset or a frame that cannot be read."""
    path, _, index = spec.rpartition(":")
    if not path or re.fullmatch(r"-?[0-9]{1,18}", index) is None:
        raise UsageError(f"--frame-like: expected DATASET:INDEX (INDEX a frame's number from 0), got {spec!r}")
    try:
        frames = _capture(path, K)
        if not 0 <= int(index) < len(frames):
            raise UsageError(f"--frame-like: {path} has {len(frames)} frames (0..{len(frames) - 1}), got {index}")
        return frames.source(int(index)).view()
    except (OSError, ValueError) as exc:
        raise ValueError(f"--frame-like: {exc}") from None


def run_render(args) -> int:
    if not (args.frame_like or args.pose or args.trajectory):
        raise UsageError("give the view(s): --frame-like DATASET:INDEX, --pose FILE or --trajectory FILE")
    if args.map != "rgb" and (args.colour or args.background):
        raise UsageError(f"--{'colour' if args.colour else 'background'}: only with --map rgb (got --map {args.map})")
    if not (args.depth_scale > 0 and np.isfinite(args.depth_scale)):
        raise UsageError(f"--depth-scale: expected a positive number of units per metre, got {args.depth_scale:g}")
    with warnings_on_stderr():
        views = render_views(args)
    paths = output_paths(args.output, len(views))
    suffixes = {path.suffix.lower() for path in paths}
    if not suffixes <= {".png", ".npy"}:
        raise UsageError(f"-o: expected .png files (or .npy for the map's own values), got {args.output!r}")
    with connect(args) as client:  # one process and one connection for every view
        session = client.session(args.session)
        if args.map == "rgb":  # the other maps do not depend on the colours
            wait_solved(session, args.wait_solved)
        for view, path in zip(views, paths):
            data = view_file(session, args.map, view, path.suffix.lower() == ".npy", args, args.background)
            with writing("-o", path):
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            print(path, flush=True)
    return 0


def view_file(session, kind: str, view, values: bool, args, background) -> bytes:
    """The bytes of one view's file: the ``kind`` map (`MAPS`) as a PNG, or with ``values`` as .npy."""
    K, c2w, width, height = view
    if kind == "rgb" and not values:
        return session.render_png(K, c2w, width, height, args.max_gaussians, background, args.colour)
    if kind == "labels" and not values:
        return session.segmentation_png(K, c2w, width, height, args.max_gaussians)
    if kind == "features" and not values:
        return session.features_preview_png(K, c2w, width, height, args.max_gaussians)
    if kind in ("rgb", "depth"):
        maps = session.render(K, c2w, width, height, args.max_gaussians, background, args.colour)
        if kind == "depth" and not values:
            return depth_png(maps["depth"], args.depth_scale)
        array = maps[kind]
    elif kind == "labels":
        labels = session.segmentation(K, c2w, width, height, args.max_gaussians)["labels"]
        array = np.where(labels == NO_LABEL, -1, labels).astype(np.int16)
    else:
        array = session.features(K, c2w, width, height, args.max_gaussians)["features"]
    out = io.BytesIO()
    np.save(out, array)
    return out.getvalue()


def depth_png(depth: np.ndarray, scale: float) -> bytes:  # float32 [H, W] metres -> 16-bit PNG bytes
    """Depth in ``scale`` units a metre as a 16-bit greyscale PNG, 0 where nothing is drawn; depth past
    16 bits of units is written as 0 too (missing, as a depth camera stores it), with a warning."""
    import imagecodecs

    units = np.rint(np.asarray(depth, np.float64) * scale)
    over = units >= DEPTH_INVALID_CODE  # reads as missing too
    if over.any():
        print(f"warning: depth: {int(over.sum())} pixels lie beyond {(DEPTH_INVALID_CODE - 1) / scale:g} m, more than 16 bits of "
              f"--depth-scale {scale:g} units; written as 0 (missing)", file=sys.stderr)
    return imagecodecs.png_encode(np.where(over, 0, units).astype(np.uint16))


# -- export -------------------------------------------------------------------------------------
def add_export(p: argparse.ArgumentParser) -> None:
    add_connection(p)
    p.add_argument("--session", type=session_id, required=True)
    p.add_argument("--max-gaussians", type=int, default=None)
    p.add_argument("--mesh", action="store_true",
                   help="the surface as a coloured triangle mesh (PLY: vertex colours and faces) instead of the Gaussians")
    add_wait_solved(p, "exports of the Gaussians")
    p.add_argument("-o", "--output", required=True, help="file ending in .ply or .splat (.ply with --mesh)")


def run_export(args) -> int:
    suffix = Path(args.output).suffix.lower()
    if suffix not in ((".ply",) if args.mesh else (".ply", ".splat")):
        raise UsageError(f"-o: expected a {'.ply' if args.mesh else '.ply or .splat'} file name, got {args.output!r}")
    if args.mesh and args.max_gaussians is not None:
        raise UsageError("--max-gaussians: a level of detail of the Gaussians; --mesh exports the surface")
    with connect(args) as client:
        session = client.session(args.session)
        if not args.mesh:  # the mesh's colours are the fused ones
            wait_solved(session, args.wait_solved)
        with writing("-o", args.output):  # missing folders are created, as render does
            if args.mesh:
                path = session.export_mesh(args.output)
            else:
                path = (session.export_ply if suffix == ".ply" else session.export_splat)(args.output, args.max_gaussians)
    print(path)
    return 0
