"""The ``canonical`` command line.

    canonical serve [--host H] [--port P] [--data-dir D] [--threads N] [--cluster [--address A] [--owners N]]
    canonical stream DATASET --url URL [--session ID | [--voxel-size S] [--set PATH=VALUE ...]] [--stride K] [--max-frames N] [--scale F] [--strict] [--json]
    canonical render --url URL --session ID (--frame-like DATASET:INDEX ... | (--pose FILE | --trajectory FILE) (--K fx,fy,cx,cy --size WxH | --frame-like DATASET:INDEX)) -o out.png|'view_{i}.png'|DIR/
    canonical export --url URL --session ID -o scene.ply|scene.splat
    canonical export --url URL --session ID --mesh -o surface.ply
    canonical sessions --url URL [--json] [--prune [--dry-run]]
    canonical view --url URL --session ID [--no-browser]   (print the web viewer's URL, open a browser)
    canonical demo [DATASET] [--out DIR]   (start a service, stream a sample, write a render and a PLY)
    canonical eval DATASET --views 2,4,8,16 --out DIR [--methods ...] [--noise ...]
    canonical depth DATASET --out DIR [--sources 2]   (plane-sweep depth + uncertainty pictures)
    canonical train CAPTURE... --out MODEL.safetensors [--seed S] [--steps K] [--minutes M] [--device cpu|cuda]

Every subcommand is one entry of `COMMANDS`: a name mapped to (add_arguments, run). To add one,
write both functions and register them: ``COMMANDS["demo"] = Command(add_demo, run_demo, "...")``.
The CLI talks to the service over HTTP (`client.sdk`); ``serve`` (which runs it under uvicorn) and
``repair`` (which works on a stopped service's data directory) import it where they run, so the module
itself imports nothing from ``server``. Datasets are read client-side with canonical_core.datasets.

For scripts, the commands that talk to a service print their result alone on stdout: ``stream`` the
session's id (``S=$(canonical stream ...)``), ``render`` and ``export`` the paths they wrote, one a
line, ``view`` the page's URL, ``sessions`` its table (``--prune``: a line per removed session); ``--json`` (stream, sessions, poses) prints a
JSON result instead. Progress, warnings and summaries go to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import re
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import httpx
import numpy as np

from .sdk import CanonicalError, Client, Session, StreamRefused, default_url, exact_sensor_depth


@dataclass(frozen=True)
class Command:
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str


class UsageError(Exception):
    """An option's value that cannot work whatever the files or the service hold; the message names
    the option. `main` prints it on one line and exits with 2, as argparse does for its own errors."""


def _add_connection(p: argparse.ArgumentParser) -> None:
    p.add_argument("--url", default=default_url(),
                   help="service base URL (default: $CANONICAL_URL or http://127.0.0.1:8000)")
    p.add_argument("--token", default=None, help="bearer token (default: $CANONICAL_API_TOKEN)")


def _client(args) -> Client:
    return Client(args.url, token=args.token)


def _add_json(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--json", action="store_true", help=f"print {what} as JSON on stdout (for scripts)")


@contextlib.contextmanager
def warnings_on_stderr():
    """Warnings raised inside (a loader's skipped frames, say) as one line each on stderr, after it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        yield
    for warning in caught:
        print(f"warning: {warning.message}", file=sys.stderr)


# -- serve --------------------------------------------------------------------------------------
def add_serve(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default=None, help="bind address (default: $CANONICAL_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default: $CANONICAL_PORT or 8000)")
    p.add_argument("--data-dir", default=None, help="session storage (default: $CANONICAL_DATA_DIR or ./data)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads per job (default: $CANONICAL_THREADS or all)")
    p.add_argument("--log-level", default="info")
    p.add_argument("--cluster", action="store_true",
                   help="run on Ray Serve (needs the [cluster] extra): start a local Ray cluster, or join --address; "
                        "--data-dir must then be a folder every node mounts")
    p.add_argument("--address", default=None, help="with --cluster: the Ray cluster to join (default: $RAY_ADDRESS, "
                                                   "else a local one)")
    p.add_argument("--owners", type=int, default=None, help="with --cluster: session owner processes "
                                                            "(default: $CANONICAL_OWNERS or 2)")


SERVE_SETTINGS = ("host", "port", "data_dir", "threads", "owners")  # the service's settings `serve` has options for


def run_serve(args) -> int:
    if not args.cluster and (args.address is not None or args.owners is not None):
        print("error: --address and --owners need --cluster", file=sys.stderr)
        return 2
    # Settings travel as CANONICAL_* variables to the service's own settings class (server.settings).
    for name in SERVE_SETTINGS:
        value = getattr(args, name)
        if value is not None:
            os.environ[f"CANONICAL_{name.upper()}"] = str(value)
    # The service's threads (requests, folds, decodes, log and archive writers, colour solves) each
    # start OpenMP teams on a few cores: idle OpenMP threads sleep instead of spinning against the
    # others (set OMP_WAIT_POLICY to choose otherwise; it must be set before torch or numba loads).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    settings = serve_settings(args)
    if args.cluster:
        from server.cluster.claims import ClaimsDoNotFit
        from server.cluster.serve import serve_forever  # imports Ray: only in cluster mode

        try:
            return serve_forever(settings, args.address)
        except ClaimsDoNotFit as exc:  # claims the cluster cannot place: one line naming the setting
            raise UsageError(f"{_setting_source(args, exc.setting)}: {exc.problem}") from None
    import uvicorn

    from server.app import create_app
    from server.session_errors import DataDirLocked

    # threads reach the service as CANONICAL_THREADS (numba.set_num_threads per worker thread):
    # NUMBA_NUM_THREADS must not change after numba is imported, or its next compile fails.
    app = create_app(settings)
    try:  # the directory's lock before uvicorn starts: a refusal is one line, not the lifespan's traceback
        app.state.store.lock_dir()
    except DataDirLocked as exc:
        print(f"error: {_setting_source(args, 'data_dir')}: {str(exc).removeprefix('data_dir: ')}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"error: {_setting_source(args, 'data_dir')}: cannot create {exc.filename or settings.data_dir}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return 1
    # The protocol closes connections whose request head is late (slowloris); bodies get 408 in the app.
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=args.log_level,
                http="server.protocol:HeadTimeoutH11Protocol", timeout_keep_alive=5)
    return 0


def _setting_source(args, name: str) -> str:
    """Where a service setting came from: its ``serve`` option, else its CANONICAL_* variable."""
    given = name in SERVE_SETTINGS and getattr(args, name, None) is not None
    return f"--{name.replace('_', '-')}" if given else f"CANONICAL_{name.upper()}"


def serve_settings(args):
    """The service's settings (`server.settings.Settings`, or the cluster's) from the environment that
    `run_serve` filled; UsageError naming the option or variable of the first invalid one."""
    from pydantic import ValidationError

    if args.cluster:
        from server.cluster.settings import ClusterSettings as kind
    else:
        from server.settings import Settings as kind
    try:
        return kind()
    except ValidationError as exc:
        first = exc.errors()[0]
        name = str(first["loc"][0]) if first["loc"] else "settings"
        message = first["msg"].removeprefix("Value error, ")
        raise UsageError(f"{_setting_source(args, name)}: {message[:1].lower()}{message[1:]}, got {first['input']}") from None


# -- repair -------------------------------------------------------------------------------------
def add_repair(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", default=None, help="the service's data directory (default: $CANONICAL_DATA_DIR or "
                                                    "./data); the service must be stopped")
    p.add_argument("--session", default=None, help="the session to repair (default: list the sessions that need it)")
    p.add_argument("--action", choices=["truncate", "skip"], default=None,
                   help="truncate: keep the frames logged before the damage; skip: keep every intact frame "
                        "(the log as it was stays in the session's quarantine/ folder)")


def run_repair(args) -> int:
    # Works on the data directory itself, not over HTTP: the one place the CLI imports the service's code.
    from server.session_errors import DataDirLocked, Unrestorable
    from server.store import SessionStore

    data_dir = args.data_dir or os.environ.get("CANONICAL_DATA_DIR", "./data")
    store = SessionStore(data_dir, max_sessions=1 << 30)
    if not store.root.is_dir():  # repair creates nothing: a mistyped path is said, not made a new directory
        problem = "does not exist" if not os.path.exists(data_dir) else \
            f"is not a data directory (no {store.root.name}/ in it)"
        print(f"error: {_setting_source(args, 'data_dir')}: {data_dir} {problem}", file=sys.stderr)
        return 1
    try:
        if args.session is None:
            store.open()
            for session_id, problem in sorted(store.unavailable.items()):
                print(f"{session_id}: {problem}")
            print(f"{len(store.unavailable)} of {len(store) + len(store.unavailable)} sessions need repair")
        else:
            print(store.repair(args.session, args.action))
    except (DataDirLocked, Unrestorable, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        store.close()
    return 0


# -- stream -------------------------------------------------------------------------------------
def add_stream(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="a capture canonical_core.datasets.load_dataset reads (tsdf-fusion, TUM, transforms.json, deep-video-mvs, Redwood, label-fusion)")
    _add_connection(p)
    target = p.add_mutually_exclusive_group()
    target.add_argument("--session", help="stream into this existing session, after the frames it already has "
                                           "(give the same dataset, --stride and --max-frames to resume)")
    target.add_argument("--voxel-size", type=float, help="a new session's voxel size, metres (default: chosen by the "
                                                         "service from the first frame, 6 pixel footprints at its median depth)")
    p.add_argument("--stride", type=int, default=1, help="keep every k-th frame")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--scale", type=float, default=1.0, help="resize frames by this factor before sending (e.g. 0.5); "
                                                             "frames without depth over the service's limit for them "
                                                             "are downscaled to it anyway")
    p.add_argument("--in-flight", type=positive_int, default=IN_FLIGHT, help="frames posted at once (the service "
                                                                              "folds them in order; 1: one at a time)")
    p.add_argument("--strict", action="store_true", help="refuse a capture that lists frames whose images are missing "
                                                         "(default: skip them, with a warning that counts them)")
    _add_json(p, "the session's stats when the stream ends, with the frames sent and the seconds taken")
    p.add_argument("--set", dest="settings", action="append", default=[], type=session_setting, metavar="PATH=VALUE",
                   help="a setting of the new session (a public SceneConfig field, groups with a dot, VALUE read as "
                        "the field's type), e.g. --set colour_solve.views=16 --set free_space.margin=3; repeatable")


def positive_int(text: str) -> int:
    """An argument that must be a whole number of at least 1 (a usage error otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def session_setting(text: str) -> tuple[str, object]:
    """``PATH=VALUE`` -> (PATH, VALUE), checked and typed by the library's settings definition
    (`canonical_core.config.parse_setting`): an unknown or evaluation-only setting, or a value
    of the wrong type or out of bounds, is a usage error naming the setting.

    Example:
        >>> session_setting("colour_solve.views=16"), session_setting("depth.sources=3")
        (('colour_solve.views', 16), ('depth.sources', 3))
    """
    from canonical_core.config import parse_setting

    try:
        return parse_setting(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def frame_arrays(frame, scale: float = 1.0, sensor_units: bool = False) -> dict:
    """A canonical_core Frame -> keyword arguments of `Session.add_frame` (numpy), optionally resized.

    With ``sensor_units``, depth that 16-bit sensor units hold exactly (depth read from a 16-bit depth
    image) travels as those units and their ``depth_scale``: half the depth's bytes, and the service
    folds the same float32 metres."""
    camera = frame.camera
    rgb = frame.rgb.numpy()
    depth = None if frame.depth is None else frame.depth.numpy()
    if scale != 1.0:
        from PIL import Image

        camera = camera.scaled(scale)
        size = (camera.width, camera.height)
        rgb = np.array(Image.fromarray(rgb).resize(size, Image.BILINEAR))
        if depth is not None:  # nearest: averaging depth across edges invents surfaces
            depth = np.array(Image.fromarray(np.ascontiguousarray(depth, np.float32)).resize(size, Image.NEAREST))
    out = {"rgb": rgb, "K": camera.K64(), "c2w": camera.c2w64(), "depth": depth, "frame_id": frame.frame_id}
    sensor = exact_sensor_depth(depth) if sensor_units and depth is not None else None
    if sensor is not None:
        out["depth"], out["depth_scale"] = sensor
    if scale == 1.0:
        for name in ("depth_std", "features", "labels"):
            value = getattr(frame, name)
            if value is not None:
                out[name] = value.numpy()
    return out


def frame_files(source) -> dict | None:
    """A capture's frame (a `FrameSequence.source`) as keyword arguments of `Session.add_frame` that
    carry its files' own bytes: PNG or JPEG colour, 16-bit PNG depth with its ``depth_scale``. Nothing
    is decoded and encoded again (the client's CPU is often the service's), the capture's own
    compression is what travels and what the service keeps, and the service decodes the very frame
    the loader reads. None where the loader changes the images it reads (undistortion, a size to
    check, depth that is not a PNG): send `frame_arrays` then."""
    from canonical_core.datasets.files import IMAGE_SUFFIXES, RGBDFile

    if not isinstance(source, RGBDFile) or source.distortion is not None or source.size is not None:
        return None
    if source.color.suffix.lower() not in IMAGE_SUFFIXES or (source.depth is not None and source.depth.suffix.lower() != ".png"):
        return None
    out = {"rgb": source.color.read_bytes(), "K": source.K, "c2w": source.c2w, "frame_id": source.frame_id}
    if source.depth is not None:
        out["depth"], out["depth_scale"] = source.depth.read_bytes(), source.depth_scale
    return out


def capture_frames(frames, scale: float = 1.0, start: int = 0) -> Iterator[dict]:
    """Frames ``start`` .. end of a capture as `Session.add_frame` keyword arguments, read one at a
    time: its files as they are (`frame_files`) where they can be, else decoded (`frame_arrays`,
    depth in its 16-bit sensor units)."""
    for i in range(start, len(frames)):
        files = frame_files(frames.source(i)) if scale == 1.0 else None
        yield files if files is not None else frame_arrays(frames[i], scale, sensor_units=True)


IN_FLIGHT = 3  # frames `canonical stream` keeps posted at once: one folding, the next ones read and decoded


class FirstFrameSession:
    """A new session that exists once its first frame is in: the first `add_frame` creates it (with
    ``settings``, as `Client.create_session`) and, if the service refuses that frame or the call is
    interrupted, deletes it again, so a stream that fails at its start leaves no empty session
    behind. ``created(session)`` is called once the first frame is in; ``session`` is None until then."""

    def __init__(self, client: Client, settings: dict, created: Callable | None = None):
        self.client, self.settings, self.created = client, settings, created
        self.session = None

    def add_frame(self, **frame) -> dict:
        if self.session is not None:
            return self.session.add_frame(**frame)
        session = self.client.create_session(**self.settings)
        try:
            report = session.add_frame(**frame)
        except BaseException:
            with contextlib.suppress(Exception):  # the refusal is what the user needs to see, not this
                session.delete()
            raise
        self.session = session
        if self.created is not None:
            self.created(session)
        return report

    def add_frames(self, frames, in_flight: int = IN_FLIGHT, first_index: int | None = None) -> Iterator[dict]:
        """`Session.add_frames`, the first frame posted alone (it creates the session)."""
        frames = iter(frames)
        if self.session is None:
            first = next(frames, None)
            if first is None:
                return
            yield self.add_frame(**first)
            first_index = 1
        yield from self.session.add_frames(frames, in_flight, first_index)


def stream_frames(session, frames, scale: float = 1.0, start: int = 0, in_flight: int = IN_FLIGHT) -> tuple[int, float]:
    """Post frames ``start`` .. end to ``session`` (a `Session` or a `FirstFrameSession`) with a progress
    bar, ``in_flight`` at once (`Session.add_frames`: folded in order); returns (frames sent, elapsed
    seconds). The fold reports' warnings and those raised while a frame is read and sent (a frame
    downscaled to the service's limit) go to stderr, each kind once.

    Ctrl-C stops after the frames in flight; a refused frame stops the stream (`StreamRefused`)."""
    from tqdm import tqdm

    t0, new, sent = time.perf_counter(), 0, 0
    shown: set[str] = set()
    with tqdm(total=len(frames), initial=start, unit="frame", desc=frames.name) as bar, \
            warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            first_index = start if isinstance(session, Session) else None
            reports = session.add_frames(capture_frames(frames, scale, start), in_flight, first_index)
            for i, report in enumerate(reports, start):
                sent += 1
                new += report["new_voxels"]
                raised = [str(w.message) for w in caught]
                caught.clear()
                for warning in raised + report.get("warnings", []):
                    kind = re.sub(r"[0-9.,%]+", "#", warning)  # each kind of warning once, whatever its figures
                    if kind not in shown:
                        shown.add(kind)
                        bar.write(f"frame {i}: {warning}", file=sys.stderr)
                bar.set_postfix(voxels=new, refresh=False)
                bar.update()
        except KeyboardInterrupt:
            bar.close()
            raise StreamInterrupted(sent, time.perf_counter() - t0) from None
    return sent, time.perf_counter() - t0


class StreamInterrupted(Exception):
    """Ctrl-C during `stream_frames`: ``sent`` frames were acknowledged in ``elapsed`` seconds."""

    def __init__(self, sent: int, elapsed: float):
        super().__init__(f"interrupted after {sent} frames")
        self.sent, self.elapsed = sent, elapsed


def _stream_summary(n: int, elapsed: float, session, stats: dict) -> str:
    size = "" if stats.get("voxel_size") is None else f" of {stats['voxel_size'] * 1000:g} mm"
    sensor = "" if stats.get("sensor", "auto") == "auto" else f"; {stats['sensor']} noise model ({stats['chosen']['sensor']})"
    return (f"{n} frames in {elapsed:.1f} s ({n / max(elapsed, 1e-9):.2f} frames/s); "
            f"session {session.id}: {stats['frames']} frames, {stats['voxels']} voxels{size}, "
            f"{stats['gaussians']} Gaussians{sensor}")


def run_stream(args) -> int:
    from canonical_core.datasets import load_dataset
    from canonical_core.config import settings_from_pairs

    if args.session and args.settings:
        print("--set: settings belong to a new session (without --session), not to an existing one", file=sys.stderr)
        return 2
    if any(name == "voxel_size" for name, _ in args.settings):
        print("--set: voxel_size is set by --voxel-size", file=sys.stderr)
        return 2
    with warnings_on_stderr():
        frames = load_dataset(args.dataset, stride=args.stride, max_frames=args.max_frames, strict=args.strict)

    def announce(session) -> None:  # the id on stdout as soon as the session holds a frame: S=$(canonical stream ...)
        if not args.json:
            from tqdm import tqdm

            tqdm.write(session.id, file=sys.stdout)  # on a terminal, above the progress bar rather than through it
            sys.stdout.flush()

    with _client(args) as client:
        start = 0
        if args.session:
            target = client.session(args.session)
            start = min(target.stats()["frames"], len(frames))  # resume after the frames it already has
            print(f"session {target.id}: resuming after its {start} frames", file=sys.stderr)
            announce(target)
        else:
            voxel = {} if args.voxel_size is None else {"voxel_size": args.voxel_size}
            target = FirstFrameSession(client, {**voxel, **settings_from_pairs(args.settings)}, created=announce)
        interrupted, refused = False, None
        t0 = time.perf_counter()
        try:
            sent, elapsed = stream_frames(target, frames, args.scale, start, args.in_flight)
        except StreamInterrupted as stop:
            sent, elapsed, interrupted = stop.sent, stop.elapsed, True
        except StreamRefused as exc:
            sent, elapsed, refused = exc.index - start, time.perf_counter() - t0, exc
        session = target.session if isinstance(target, FirstFrameSession) else target
        if session is None:  # no frame went in: no session was made
            print(("interrupted" if interrupted else f"{frames.name}: no frames to stream")
                  + "; no session was created", file=sys.stderr)
            return 130 if interrupted else 1
        stats = session.stats()
        if interrupted:  # the frames in flight at Ctrl-C were folded too
            sent = stats["frames"] - start
        summary = _stream_summary(sent, elapsed, session, stats)
        if interrupted or refused:
            summary = f"{'interrupted' if interrupted else 'stopped'}: {summary}; continue with --session {session.id}"
        if refused:
            print(f"error: {refused}", file=sys.stderr)
            print(summary, file=sys.stderr)
            return 1
        print(summary, file=sys.stderr)
        if args.json:
            print(json.dumps({**stats, "sent": sent, "seconds": round(elapsed, 3), "interrupted": interrupted}))
    return 130 if interrupted else 0


# -- render -------------------------------------------------------------------------------------
def add_render(p: argparse.ArgumentParser) -> None:
    _add_connection(p)
    p.add_argument("--session", required=True)
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
    p.add_argument("--K", help="fx,fy,cx,cy in pixels (with --pose or --trajectory)")
    p.add_argument("--size", type=image_size_arg, metavar="WxH", help="image size (with --K), e.g. 640x480")
    p.add_argument("--width", type=int, help="image width (or --size)")
    p.add_argument("--height", type=int, help="image height (or --size)")
    p.add_argument("--max-gaussians", type=int, default=None)
    p.add_argument("--background", default=None, help="r,g,b in [0, 1]")
    p.add_argument("--colour", choices=["normalised", "composited"], default=None,
                   help="normalised (the service's default: each drawn pixel the surface's expected colour, not darkened "
                        "where splats cover it only in part) or composited (the blend over the background)")
    p.add_argument("-o", "--output", required=True,
                   help="the PNG to write; for several views a pattern with {i}, the view's index (e.g. "
                        "'views/{i:03d}.png'), or a folder (DIR/: view_0000.png, ...). The paths written are printed")


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
def _capture(path: str):
    """A capture read once however many --frame-like views name it."""
    from canonical_core.datasets import load_dataset

    return load_dataset(path)


def view_poses(path: str) -> list[np.ndarray]:
    """The camera-to-world poses of a --pose or --trajectory file, in file order: one 4x4 (or 3x4)
    matrix written over its lines, else one pose a line (`read_pose_file`)."""
    from canonical_core.camera import validate_pose

    try:
        matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError:  # not one block of numbers: pose lines with keys, or malformed (read_pose_file says where)
        matrix = None
    if matrix is not None and matrix.shape in ((4, 4), (3, 4)):
        return [validate_pose(matrix, str(path))]
    return list(read_pose_file(path).values())


def render_views(args) -> list[tuple[np.ndarray, np.ndarray, int, int]]:
    """(K, c2w, width, height) of each view the arguments name, in order: each --frame-like's camera,
    or each pose of --pose / --trajectory with --K and --size (else the --frame-like camera's)."""
    cameras = [frame_like_camera(spec) for spec in args.frame_like]
    pose_file = args.pose or args.trajectory
    if pose_file is None:
        if args.K or args.size or args.width or args.height:
            raise SystemExit("--K and --size go with --pose or --trajectory (--frame-like brings its own)")
        return [(c.K64(), c.c2w64(), c.width, c.height) for c in cameras]
    width, height = args.size or (args.width, args.height)
    if args.K:
        fx, fy, cx, cy = (float(x) for x in args.K.split(","))
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        if not (width and height):
            if len(cameras) != 1:
                raise SystemExit("--K needs --size WxH (or one --frame-like whose image size to take)")
            width, height = cameras[0].width, cameras[0].height
    elif len(cameras) == 1:
        K, width, height = cameras[0].K64(), width or cameras[0].width, height or cameras[0].height
    else:
        raise SystemExit("--pose and --trajectory need --K fx,fy,cx,cy and --size WxH, or one --frame-like "
                         "DATASET:INDEX whose intrinsics and image size to take")
    return [(K, c2w, width, height) for c2w in view_poses(pose_file)]


def output_paths(output: str, count: int) -> list[Path]:
    """Where each of ``count`` views goes: ``output`` with its {i} filled in, or in the folder
    ``output`` (view_0000.png, ...), or, for one view, ``output`` itself."""
    if "{" in output:
        try:
            paths = [Path(output.format(i=i)) for i in range(count)]
        except (KeyError, IndexError, ValueError) as exc:
            raise SystemExit(f"-o: expected a pattern with {{i}} (e.g. view_{{i:03d}}.png), got {output!r} ({exc!r})") from None
        if len(set(paths)) < count:
            raise SystemExit(f"-o: {output!r} names one file for several views; put {{i}} in it")
        return paths
    if output.endswith(("/", os.sep)) or Path(output).is_dir():
        return [Path(output) / f"view_{i:04d}.png" for i in range(count)]
    if count > 1:
        raise SystemExit(f"-o: {count} views need a pattern with {{i}} (e.g. view_{{i:03d}}.png) or a folder, got {output!r}")
    return [Path(output)]


def frame_like_camera(spec: str):
    """The camera of ``--frame-like DATASET:INDEX``: UsageError for a spec without an index or an index
    the dataset does not have, ValueError naming the option for a dataset that cannot be read."""
    path, _, index = spec.rpartition(":")
    if not path or re.fullmatch(r"-?[0-9]{1,18}", index) is None:
        raise UsageError(f"--frame-like: expected DATASET:INDEX (INDEX a frame's number from 0), got {spec!r}")
    try:
        frames = _capture(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--frame-like: {exc}") from None
    if not 0 <= int(index) < len(frames):
        raise UsageError(f"--frame-like: {path} has {len(frames)} frames (0..{len(frames) - 1}), got {index}")
    return frames[int(index)].camera


def run_render(args) -> int:
    if not (args.frame_like or args.pose or args.trajectory):
        print("render: give the view(s): --frame-like DATASET:INDEX, --pose FILE or --trajectory FILE", file=sys.stderr)
        return 2
    with warnings_on_stderr():
        views = render_views(args)
    paths = output_paths(args.output, len(views))
    background = None if args.background is None else [float(x) for x in args.background.split(",")]
    with _client(args) as client:  # one process and one connection for every view
        session = client.session(args.session)
        for (K, c2w, width, height), path in zip(views, paths):
            png = session.render_png(K, c2w, width, height, args.max_gaussians, background, args.colour)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(png)
            print(path, flush=True)
    return 0


# -- export -------------------------------------------------------------------------------------
def add_export(p: argparse.ArgumentParser) -> None:
    _add_connection(p)
    p.add_argument("--session", required=True)
    p.add_argument("--max-gaussians", type=int, default=None)
    p.add_argument("--mesh", action="store_true",
                   help="the surface as a coloured triangle mesh (PLY: vertex colours and faces) instead of the Gaussians")
    p.add_argument("-o", "--output", required=True, help="file ending in .ply or .splat (.ply with --mesh)")


def run_export(args) -> int:
    suffix = Path(args.output).suffix.lower()
    if suffix not in ((".ply",) if args.mesh else (".ply", ".splat")):
        raise SystemExit(f"-o: expected a {'.ply' if args.mesh else '.ply or .splat'} file name, got {args.output!r}")
    if args.mesh and args.max_gaussians is not None:
        raise SystemExit("--max-gaussians: a level of detail of the Gaussians; --mesh exports the surface")
    with _client(args) as client:
        session = client.session(args.session)
        if args.mesh:
            path = session.export_mesh(args.output)
        else:
            path = (session.export_ply if suffix == ".ply" else session.export_splat)(args.output, args.max_gaussians)
    print(path)
    return 0


# -- sessions -----------------------------------------------------------------------------------
def add_sessions(p: argparse.ArgumentParser) -> None:
    _add_connection(p)
    _add_json(p, "the sessions (the service's summaries, and each one's age_s and idle_s in seconds); with --prune "
                 "its report")
    p.add_argument("--prune", action="store_true", help=(
        "apply the service's retention policy now (CANONICAL_SESSION_TTL_S, CANONICAL_DISK_BUDGET_BYTES): print a "
        "line per removed session (id, reason, idle time, disk); never one active in the last 24 hours"))
    p.add_argument("--dry-run", action="store_true", help="with --prune: remove nothing, print what would be removed")


def human_bytes(n: int | None) -> str:
    """Bytes for people: ``human_bytes(3_500_000)`` is '3.3 MiB'."""
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def human_age(seconds: float) -> str:
    """A duration for people: ``human_age(5400)`` is '1.5 h'."""
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 36 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} d"


def run_sessions(args) -> int:
    if args.dry_run and not args.prune:
        raise SystemExit("--dry-run goes with --prune")
    if args.prune:
        return run_prune(args)
    with _client(args) as client:
        sessions = client.sessions()
    now = time.time()
    if args.json:
        print(json.dumps([{**s, "age_s": round(now - s["created"], 3) if s["created"] else None,
                           "idle_s": round(now - s["last_active"], 3) if s.get("last_active") else None}
                          for s in sessions]))
        return 0
    rows = [("id", "voxel", "frames", "memory", "disk", "age", "state")]
    for s in sessions:
        voxel = "-" if s.get("voxel_size") is None else f"{s['voxel_size'] * 1000:g} mm"
        age = human_age(now - s["created"]) if s["created"] else "-"  # an unavailable session may not say
        frames = "-" if s["frames"] is None else str(s["frames"])
        rows.append((s["id"], voxel, frames, human_bytes(s.get("memory_bytes")), human_bytes(s.get("disk_bytes")), age,
                     s["state"]))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    for row in rows:  # the id and the state left-aligned, the figures right-aligned
        cells = [cell.ljust(w) if k in (0, 6) else cell.rjust(w) for k, (cell, w) in enumerate(zip(row, widths))]
        print("  ".join(cells).rstrip())
    return 0


def run_prune(args) -> int:
    """``sessions --prune``: the removed sessions on stdout (one a line), the summary on stderr."""
    with _client(args) as client:
        report = client.prune_sessions(dry_run=args.dry_run)
    if args.json:
        print(json.dumps(report))
    else:
        now = time.time()
        for s in report["removed"]:
            print(f"{s['id']}  {s['reason']}  idle {human_age(now - s['last_active'])}  {human_bytes(s['disk_bytes'])}")
    ttl = "none" if report["session_ttl_s"] is None else human_age(report["session_ttl_s"])
    print(f"{'would remove' if report['dry_run'] else 'removed'} {len(report['removed'])} sessions "
          f"({human_bytes(report['freed_bytes'])}) of a data directory of {human_bytes(report['data_dir_bytes'])}; "
          f"time to live {ttl}, disk budget {human_bytes(report['disk_budget_bytes']) if report['disk_budget_bytes'] else 'none'}, "
          f"none active in the last {human_age(report['floor_s'])}", file=sys.stderr)
    return 0


# -- view ---------------------------------------------------------------------------------------
def add_view(p: argparse.ArgumentParser) -> None:
    _add_connection(p)
    p.add_argument("--session", required=True, help="session id")
    p.add_argument("--no-browser", action="store_true", help="only print the URL")


def viewer_url(base: str, session_id: str) -> str:
    """The web viewer's page of a session (the token never goes into it: the page asks for it)."""
    return f"{base.rstrip('/')}/sessions/{session_id}/view"


def has_display() -> bool:
    """Whether a graphical browser can open here (a console browser would take over the terminal)."""
    return sys.platform in ("darwin", "win32") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run_view(args) -> int:
    with _client(args) as client:
        client.session(args.session)  # 404 for an unknown id, 401 for a missing token: said before any URL
    url = viewer_url(args.url, args.session)
    print(url)
    if args.token or os.environ.get("CANONICAL_API_TOKEN"):
        print("the page asks for the API token once (kept in the browser tab, sent as a bearer header)", file=sys.stderr)
    if not args.no_browser and has_display():
        import webbrowser

        webbrowser.open(url)
    return 0


# -- poses --------------------------------------------------------------------------------------
def add_poses(p: argparse.ArgumentParser) -> None:
    p.add_argument("poses", nargs="?", help="a pose file: one frame a line, 'tx ty tz qx qy qz qw' (TUM / slambook, "
                                            "quaternion scalar last) or the 16 numbers of a row-major 4x4 camera-to-world "
                                            "matrix, either optionally after the frame's key (frame_id or TUM timestamp); "
                                            "a line without a key names the frame of that arrival index (line k = frame k)")
    _add_connection(p)
    p.add_argument("--session", required=True, help="the session whose frames get the poses")
    p.add_argument("--remove", action="append", default=[], metavar="KEY",
                   help="also remove this frame (frame_id or arrival index); repeatable")
    _add_json(p, "what the correction did (the service's answer)")


def read_pose_file(path: str | Path) -> dict[str, np.ndarray]:
    """A pose file (see ``canonical poses --help``) -> {frame key: validated 4x4 c2w}; '#' comments and
    blank lines skipped. Raises ValueError naming the file and line."""
    from canonical_core.camera import validate_pose
    from canonical_core.datasets.files import parse_floats, read_text
    from canonical_core.datasets.tum import tum_pose_to_matrix

    poses: dict[str, np.ndarray] = {}
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{path}:{number}"
        key, numbers = (words[0], words[1:]) if len(words) in (8, 17) else (str(len(poses)), words)
        if len(numbers) == 7:
            c2w = tum_pose_to_matrix(parse_floats(numbers, where), where)
        elif len(numbers) == 16:
            c2w = validate_pose(parse_floats(numbers, where).reshape(4, 4), where)
        else:
            raise ValueError(f"{where}: expected 7 (tx ty tz qx qy qz qw) or 16 (a 4x4 matrix) numbers, optionally "
                             f"after a key, got {len(words)} words")
        if key in poses:
            raise ValueError(f"{where}: frame {key!r} has a pose on an earlier line")
        poses[key] = c2w
    return poses


def run_poses(args) -> int:
    if args.poses is None and not args.remove:
        print("poses: give a pose file, --remove, or both", file=sys.stderr)
        return 2
    poses = read_pose_file(args.poses) if args.poses else {}
    def progress(status: dict) -> None:  # a long re-fold runs in the service's background: show how far it is
        print(f"correction {status['correction_id']}: {status['state']}, {status['refolded']} of {status['total']} "
              "frames re-folded", file=sys.stderr)

    with _client(args) as client:
        done = client.session(args.session).update_poses(poses, remove=args.remove, progress=progress)
    print(f"session {done['id']}: {done['corrected']} poses corrected, {done['removed']} frames removed"
          + (f", {done['dropped']} not archived dropped" if done["dropped"] else "") + f"; it holds {done['frames']} frames",
          file=sys.stderr)
    if args.json:
        print(json.dumps(done))
    return 0


# -- demo ---------------------------------------------------------------------------------------
SHARED_SHELF = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def add_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", nargs="?", default=None,
                   help="a capture to fuse (default: ../shared/data/realsense_shelf, else a generated sample)")
    p.add_argument("--out", default="out/demo", help="folder for the render, comparison, PLY and the service's data")
    p.add_argument("--voxel-size", type=float, default=None, help="default: 4 mm for the shelf, 2 cm for the sample")
    p.add_argument("--port", type=int, default=0, help="port of the embedded service (default: a free one)")


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def unclaimed_port() -> int:
    """A free loopback port below the kernel's ephemeral range, for a server that binds it later while
    other processes start (a Ray cluster's GCS, raylets and workers take ephemeral ports as they
    start, so a free ephemeral port picked before them may be taken by then)."""
    import random
    import socket

    low = 32768
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low = int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        pass
    for port in random.Random().sample(range(max(1024, low - 12000), low), 200):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port below {low}")


def wait_until_healthy(url: str, proc, timeout: float) -> None:
    """Poll ``url``/healthz until it answers 200; RuntimeError if ``proc`` exits or ``timeout`` s pass."""
    import httpx

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with code {proc.returncode} before it was ready")
        try:
            if httpx.get(f"{url}/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"the service did not become ready within {timeout:g} s")


def start_service(port: int, data_dir: Path):
    """The service as a child process (the same `canonical serve` a user runs); waits for /healthz."""
    import subprocess

    proc = subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--port", str(port), "--data-dir", str(data_dir),
                             "--log-level", "warning"], cwd=Path(__file__).resolve().parents[1])
    try:
        wait_until_healthy(f"http://127.0.0.1:{port}", proc, timeout=120.0)
    except RuntimeError as exc:
        proc.kill()
        raise SystemExit(str(exc)) from None
    return proc


def run_demo(args) -> int:
    from PIL import Image

    from canonical_core.datasets import load_dataset, synthetic_rgbd, write_tsdf_fusion

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.dataset:
        path, voxel = Path(args.dataset), args.voxel_size or 0.004
    elif SHARED_SHELF.is_dir():
        path, voxel = SHARED_SHELF, args.voxel_size or 0.004
    else:  # no data on this machine: generate a small RGB-D sequence (textured boxes, exact depth)
        path, voxel = out / "sample", args.voxel_size or 0.02
        if not path.is_dir():
            write_tsdf_fusion(synthetic_rgbd(num_frames=24, width=320, height=240), path)
    frames = load_dataset(path)
    port = args.port or free_port()
    print(f"demo: fusing {len(frames)} frames of {path} at {voxel * 1000:g} mm voxels through a service on port {port}")
    service = start_service(port, out / "data")
    try:
        with Client(f"http://127.0.0.1:{port}") as client:
            new_session = FirstFrameSession(client, {"voxel_size": voxel})
            sent, elapsed = stream_frames(new_session, frames)
            session = new_session.session
            print(_stream_summary(sent, elapsed, session, session.stats()))
            view = frames[len(frames) // 2]
            cam = view.camera
            rendered = session.render(cam.K64(), cam.c2w64(), cam.width, cam.height)
            session.export_ply(out / "scene.ply")
    finally:
        service.terminate()
        service.wait(timeout=60)
    rgb = rendered["rgb"]  # uint8 [H, W, 3] on the wire
    truth = view.rgb.numpy()
    Image.fromarray(rgb).save(out / "render.png")
    Image.fromarray(np.concatenate([truth, rgb], 1)).save(out / "comparison.png")
    sq_err = ((rgb.astype(np.float64) - truth) / 255.0) ** 2
    covered = rendered["alpha"] > 0.5  # pixels the scene covers; nothing was seen at the others
    psnr = lambda mse: 10 * np.log10(1 / max(float(mse), 1e-12))  # noqa: E731
    print(f"rendered frame {view.frame_id} (an input view): PSNR {psnr(sq_err.mean()):.2f} dB over all pixels, "
          f"covered PSNR {psnr(sq_err[covered].mean()):.2f} dB on the {100 * covered.mean():.0f} % of pixels the scene covers")
    print(f"wrote {out / 'render.png'}, {out / 'comparison.png'} (truth | render) and {out / 'scene.ply'}")
    return 0


# -- depth --------------------------------------------------------------------------------------
def add_depth(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="a capture canonical_core.datasets.load_dataset reads (its depth, if any, is only compared against)")
    p.add_argument("--out", required=True, help="folder for <frame>.depth.png and <frame>.uncertainty.png")
    p.add_argument("--sources", type=int, default=2, help="source views per frame (default 2)")
    p.add_argument("--stride", type=int, default=1)
    p.add_argument("--max-frames", type=int, default=None)


def run_depth(args) -> int:
    from canonical_core.datasets import load_dataset
    from canonical_core.eval.mvs_preview import write_depth_previews

    frames = load_dataset(args.dataset, stride=args.stride, max_frames=args.max_frames)
    rows = write_depth_previews(frames, args.out, num_sources=args.sources)
    errors = [r["median_abs_rel"] for r in rows if r.get("median_abs_rel") is not None]
    summary = f"; median AbsRel vs the sensor {np.median(errors):.4f}" if errors else ""
    print(f"wrote depth and uncertainty pictures of {len(rows)} frames to {args.out}{summary}")
    return 0


# -- train --------------------------------------------------------------------------------------
def add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("captures", nargs="+", help="RGB-D capture folders (never the evaluation capture, realsense_shelf)")
    p.add_argument("--out", required=True, help="the checkpoint to write (.safetensors); the report goes to <stem>_report/")
    p.add_argument("--seed", type=int, default=0, help="seed of the samples, the step order and the initial heads (default 0)")
    p.add_argument("--steps", type=int, default=400, help="optimisation steps (default 400)")
    p.add_argument("--minutes", type=float, default=None, help="stop after this many minutes even if steps remain")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="where the decode and render run (default cpu)")
    p.add_argument("--width", type=int, default=160, help="training image width in pixels (default 160)")
    p.add_argument("--coverage-weight", type=float, default=0.0,
                   help="weight of the coverage term (1 - alpha)^2 at pixels with measured depth (default 0)")
    p.add_argument("--heads", default=None,
                   help="comma-separated heads to train (default all: opacity,free_space_penalty,offset,log_scale_delta,color_delta)")


def run_train(args) -> int:
    from canonical_core.train.loop import TrainSettings, run_training

    heads = {} if args.heads is None else {"heads": tuple(h.strip() for h in args.heads.split(",") if h.strip())}
    try:
        settings = TrainSettings(seed=args.seed, steps=args.steps, minutes=args.minutes, width=args.width,
                                 device=args.device, coverage_weight=args.coverage_weight, **heads)
    except ValueError as exc:
        print(f"canonical train: {exc}", file=sys.stderr)
        return 2
    result = run_training(args.captures, args.out, settings)
    report = Path(args.out).with_name(Path(args.out).stem + "_report")
    print(f"{result.steps} steps in {result.seconds / 60:.1f} min; wrote {args.out} and {report}/")
    print((report / "report.md").read_text())
    return 0


# -- eval ---------------------------------------------------------------------------------------
# canonical_core (torch) is imported only when `eval` is the command: the other commands start fast.
def add_eval(p: argparse.ArgumentParser) -> None:
    from canonical_core.eval.cli import configure_parser

    configure_parser(p)


def run_eval(args) -> int:
    from canonical_core.eval import cli

    return cli.run_eval(args)


COMMANDS: dict[str, Command] = {
    "serve": Command(add_serve, run_serve, "run the service (uvicorn)"),
    "stream": Command(add_stream, run_stream, "stream a dataset's frames into a session"),
    "repair": Command(add_repair, run_repair, "list or repair sessions whose files are damaged (service stopped)"),
    "render": Command(add_render, run_render, "render a session at a camera to a PNG"),
    "export": Command(add_export, run_export, "download a session's Gaussians as .ply or .splat, or with --mesh its surface mesh"),
    "sessions": Command(add_sessions, run_sessions, "list sessions"),
    "view": Command(add_view, run_view, "print a session's web viewer URL and open it in a browser"),
    "poses": Command(add_poses, run_poses, "correct a session's frame poses from a pose file (a loop closure), or remove frames"),
    "demo": Command(add_demo, run_demo, "start a service, stream a sample capture, write a render and a PLY"),
    "depth": Command(add_depth, run_depth, "estimate depth + uncertainty of a dataset's frames by plane sweep, write pictures"),
    "eval": Command(add_eval, run_eval, "evaluate methods on held-out views of a dataset (results.json/md, plots, grids)"),
    "train": Command(add_train, run_train, "train the decoder's heads on RGB-D captures, write a checkpoint and a report"),
}


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (``canonical stream: error: ...``) instead of usage + error."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``canonical`` parser; with ``only``, just that command gets its arguments (the others
    are listed by name and help), so a command never pays for another's imports."""
    parser = _Parser(prog="canonical", description="CanonicalGS Fusion: service and client.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name, command in COMMANDS.items():
        p = sub.add_parser(name, help=command.help, description=command.help)
        if only is None or name == only:
            command.add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(only=argv[0] if argv else "").parse_args(argv)
    url = getattr(args, "url", None)  # the service's URL, for the commands that talk to it
    try:
        if url is not None:
            check_service_url(url)
        return COMMANDS[args.command].run(args) or 0
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CanonicalError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except httpx.TransportError as exc:  # unreachable, refused, timed out
        where = f"--url: cannot reach the service at {url}" if url is not None else "cannot reach the service"
        print(f"error: {where}: {str(exc) or type(exc).__name__}", file=sys.stderr)
        return 1
    except (OSError, ValueError, httpx.InvalidURL) as exc:  # a missing file, a malformed number or matrix, an id no URL holds
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


def check_service_url(url: str) -> None:
    """UsageError (naming --url) unless ``url`` is an http(s) URL with a host, before any request is made."""
    try:
        parsed = httpx.URL(url)
    except httpx.InvalidURL as exc:
        raise UsageError(f"--url: {url!r} is not a valid URL: {exc}") from None
    if parsed.scheme not in ("http", "https") or not parsed.host:
        raise UsageError(f"--url: expected http://HOST[:PORT] or https://HOST[:PORT], got {url!r}")


if __name__ == "__main__":
    sys.exit(main())
