"""``stream``: a capture's frames into a new or an existing session, several in flight, with a progress
bar, a summary and a resumable stop (Ctrl-C, a refused frame)."""

from __future__ import annotations

import argparse
import contextlib
import json
import re
import sys
import time
import warnings
from typing import Callable, Iterator

from canonical_core.datasets.files import add_capture_options  # imports no torch, no numba

from ..sdk import Client, ServiceUnreachable, Session, StreamStopped
from .capture import capture_frames, load_capture
from .common import UsageError, add_connection, add_json, connect, positive_int, positive_number, session_id


def add_stream(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="a capture canonical_core.datasets.load_dataset reads (tsdf-fusion, TUM, transforms.json, deep-video-mvs, Redwood, label-fusion)")
    add_connection(p)
    target = p.add_mutually_exclusive_group()
    target.add_argument("--session", type=session_id, help="stream into this existing session, after the frames it already has "
                                           "(give the same dataset, --stride and --max-frames to resume)")
    target.add_argument("--voxel-size", type=positive_number, help="a new session's voxel size, metres (default: chosen by the "
                                                         "service from the first frame, 6 pixel footprints at its median depth)")
    add_capture_options(p)
    p.add_argument("--stride", type=positive_int, default=1, help="keep every k-th frame")
    p.add_argument("--max-frames", type=positive_int, default=None)
    p.add_argument("--scale", type=positive_number, default=1.0,
                   help="resize frames by this factor before sending (e.g. 0.5; labels and features go at their own "
                        "resolution); frames without depth over the service's limit for them are downscaled to it anyway")
    p.add_argument("--in-flight", type=positive_int, default=IN_FLIGHT, help="frames posted at once (the service "
                                                                              "folds them in order; 1: one at a time)")
    p.add_argument("--strict", action="store_true", help="refuse a capture that lists frames whose images are missing "
                                                         "(default: skip them, with a warning that counts them)")
    add_json(p, "the session's stats when the stream ends, with the frames sent and the seconds taken")
    p.add_argument("--set", dest="settings", action="append", default=[], type=session_setting, metavar="PATH=VALUE",
                   help="a setting of the new session (a public SceneConfig field, groups with a dot, VALUE read as "
                        "the field's type), e.g. --set colour_solve.views=16 --set free_space.margin=3; repeatable")


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

    Ctrl-C stops after the frames in flight; a refused frame stops the stream (`StreamRefused`, a `StreamStopped`)."""
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
                    kind = warning_kind(warning)
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


def warning_kind(warning: str) -> str:
    """What makes two warnings one kind, shown once: their words and the setting they advise
    (``range.near=0.24``: a new figure is new advice), not their other figures (shares, counts).

    Example:
        >>> warning_kind("depth: 13% under 0.28 m; range.near=0.28 ignores it")
        'depth: # under # m; range.near=0.28 ignores it'
    """
    return re.sub(r"(?<![=0-9.])[0-9][0-9.,]*%?", "#", warning)


def stream_summary(n: int, elapsed: float, session, stats: dict) -> str:
    size = "" if stats.get("voxel_size") is None else f" of {stats['voxel_size'] * 1000:g} mm"
    sensor = "" if stats.get("sensor", "auto") == "auto" else f"; {stats['sensor']} noise model ({stats['chosen']['sensor']})"
    near = stats.get("inconsistent_depth_below")  # the stream's final word on it, however its warnings went
    near = "" if near is None else f"; depth under {near:.2f} m disagrees between frames (range.near={near:.2f} ignores it)"
    return (f"{n} frames in {elapsed:.1f} s ({n / max(elapsed, 1e-9):.2f} frames/s); "
            f"session {session.id}: {stats['frames']} frames, {stats['voxels']} voxels{size}, "
            f"{stats['gaussians']} Gaussians{sensor}{near}")


def refused_files(frames, position: int) -> str:
    """`` (files: ...)``: the files of the capture's frame at ``position`` (the one the service refused),
    where its loader reads files, so that the user knows which to look at."""
    if not 0 <= position < len(frames):
        return ""
    source = frames.source(position)
    files = [str(path) for path in (getattr(source, "color", None), getattr(source, "depth", None)) if path is not None]
    return f" (files: {', '.join(files)})" if files else ""


def run_stream(args) -> int:
    if args.session and args.settings:
        raise UsageError("--set: settings belong to a new session (without --session), not to an existing one")
    if any(name == "voxel_size" for name, _ in args.settings):
        raise UsageError("--set: voxel_size is set by --voxel-size")
    frames = load_capture(args.dataset, args, stride=args.stride, max_frames=args.max_frames, strict=args.strict)

    def announce(session) -> None:  # the id on stdout as soon as the session holds a frame: S=$(canonical stream ...)
        if not args.json:
            from tqdm import tqdm

            tqdm.write(session.id, file=sys.stdout)  # on a terminal, above the progress bar rather than through it
            sys.stdout.flush()

    with connect(args) as client:
        start = held = 0
        if args.session:
            target = client.session(args.session)
            held = target.stats()["frames"]
            # resume after as many of the capture's frames as it holds; where some were removed since, the
            # frames after them that it holds are answered as held (by frame_id) and skipped
            start = min(held, len(frames))
            print(f"session {target.id}: resuming after its {held} frames", file=sys.stderr)
            announce(target)
        else:
            settings = {} if args.voxel_size is None else {"voxel_size": args.voxel_size}
            if args.settings:  # the settings' definitions (pydantic models) are slow to import: only when needed
                from canonical_core.config import settings_from_pairs

                settings |= settings_from_pairs(args.settings)
            target = FirstFrameSession(client, settings, created=announce)
        interrupted, refused = False, None
        t0 = time.perf_counter()
        try:
            sent, elapsed = stream_frames(target, frames, args.scale, start, args.in_flight)
        except StreamInterrupted as stop:
            sent, elapsed, interrupted = stop.sent, stop.elapsed, True
        except StreamStopped as exc:  # refused by the service, or a frame the client could not send
            sent, elapsed, refused = exc.index - held, time.perf_counter() - t0, exc
        except ValueError as exc:  # a frame the capture cannot give (an unreadable image): the stream stops there
            sent, elapsed, refused = None, time.perf_counter() - t0, exc
        session = target.session if isinstance(target, FirstFrameSession) else target
        if session is None:  # no frame went in: no session was made
            if refused is not None:
                print(f"error: {refused}", file=sys.stderr)
            print(("interrupted" if interrupted else f"{frames.name}: no frames streamed" if refused else
                   f"{frames.name}: no frames to stream") + "; no session was created", file=sys.stderr)
            return 130 if interrupted else 1
        client.max_retries = min(client.max_retries, 1)  # the frames' retries are over: the summary waits no half minute
        try:
            stats = session.stats()
        except ServiceUnreachable as exc:  # what was acknowledged stays told, and how to go on
            if refused is not None:
                print(f"error: {refused}", file=sys.stderr)
            done = "interrupted" if interrupted else "stopped" if refused else f"all {len(frames) - start} frames acknowledged"
            print(f"{done}; the service could not be reached for the session's summary ({exc}); "
                  f"continue with --session {session.id}", file=sys.stderr)
            return 130 if interrupted else 1
        skipped = 0
        if interrupted or sent is None:  # the frames in flight at Ctrl-C, or before the unreadable one, were folded too
            sent = stats["frames"] - held
        elif args.session and not refused:
            sent, skipped = stats["frames"] - held, sent - (stats["frames"] - held)
        if skipped > 0:
            print(f"{skipped} frames of {frames.name} from frame {start} on were in the session already: not folded again",
                  file=sys.stderr)
        summary = stream_summary(sent, elapsed, session, stats)
        if interrupted or refused:
            summary = f"{'interrupted' if interrupted else 'stopped'}: {summary}; continue with --session {session.id}"
        if refused:
            print(f"error: {refused}{refused_files(frames, start + sent) if isinstance(refused, StreamStopped) else ''}",
                  file=sys.stderr)
            print(summary, file=sys.stderr)
            return 1
        print(summary, file=sys.stderr)
        if args.json:
            print(json.dumps({**stats, "sent": sent, "seconds": round(elapsed, 3), "interrupted": interrupted}))
    return 130 if interrupted else 0
