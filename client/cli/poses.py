"""``poses``: correct a session's frame poses from a pose file (a loop closure), or remove frames; and
the pose file's reader, which ``render --trajectory`` shares."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..sdk import CanonicalError
from .common import UsageError, add_connection, add_json, connect, session_id


def add_poses(p: argparse.ArgumentParser) -> None:
    p.add_argument("poses", nargs="?", help="a pose file: one frame a line, 'tx ty tz qx qy qz qw' (TUM / slambook, "
                                            "quaternion scalar last) or the 16 numbers of a row-major 4x4 camera-to-world "
                                            "matrix, either optionally after the frame's key (frame_id or TUM timestamp); "
                                            "a line without a key names the frame of that arrival index (the k-th pose "
                                            "line = frame k, counted from 0), whatever the frames' ids")
    add_connection(p)
    p.add_argument("--session", type=session_id, required=True, help="the session whose frames get the poses")
    p.add_argument("--remove", action="append", default=[], metavar="KEY",
                   help="also remove this frame (frame_id or arrival index); repeatable")
    add_json(p, "what the correction did (the service's answer)")


def pose_text(path: str | Path) -> str:
    """A pose file's text; ValueError naming the file when it is missing or not text. Besides files,
    what reads as one: /dev/null (no poses), a pipe (``<(...)``)."""
    from canonical_core.datasets.files import read_text

    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; expected a pose file")
    if not path.exists() or path.is_file():
        return read_text(path)  # its messages: "file not found", "unreadable text file"
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: unreadable text file ({exc})") from None


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def read_pose_file(path: str | Path, text: str | None = None,
                   lines: dict | None = None) -> dict[str | int, np.ndarray]:
    """A pose file (see ``canonical poses --help``; ``text`` its text where it was read already) ->
    {frame key: validated 4x4 c2w}, a line's key as written (a string), or for a line without one its
    arrival index (an integer); '#' comments and blank lines skipped; ``lines``, when given, gets each
    key's line number. Raises ValueError naming the file and line."""
    from canonical_core.calibration import validate_pose
    from canonical_core.datasets.files import parse_floats
    from canonical_core.datasets.tum import tum_pose_to_matrix

    poses: dict[str | int, np.ndarray] = {}
    text = (pose_text(path) if text is None else text).removeprefix("\ufeff")  # a Windows editor's byte-order mark
    for number, line in enumerate(text.splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{path}:{number}"
        keyed = len(words) in (8, 17) or not _is_number(words[0])  # a TUM timestamp is a key too
        key, numbers = (words[0], words[1:]) if keyed else (len(poses), words)
        if len(numbers) == 7:
            c2w = tum_pose_to_matrix(parse_floats(numbers, where), where)
        elif len(numbers) == 16:
            c2w = validate_pose(parse_floats(numbers, where).reshape(4, 4), where)
        else:
            after = f" after the key {key!r}" if keyed else ""
            raise ValueError(f"{where}: expected 7 (tx ty tz qx qy qz qw) or 16 (a 4x4 matrix) numbers, optionally "
                             f"after a key, got {len(numbers)}{after}")
        if key in poses:
            raise ValueError(f"{where}: frame {key!r} has a pose on an earlier line")
        poses[key] = c2w
        if lines is not None:
            lines[key] = number
    return poses


def run_poses(args) -> int:
    if args.poses is None and not args.remove:
        raise UsageError("give a pose file, --remove, or both")
    lines: dict = {}
    poses = read_pose_file(args.poses, lines=lines) if args.poses else {}

    def progress(status: dict) -> None:  # a long re-fold runs in the service's background: show how far it is
        print(f"correction {status['correction_id']}: {status['state']}, {status['refolded']} of {status['total']} "
              "frames re-folded", file=sys.stderr)

    with connect(args) as client:
        try:
            done = client.session(args.session).update_poses(poses, remove=args.remove, progress=progress)
        except CanonicalError as exc:  # a key the service refused: the line of the file it came from
            number = next((n for k, n in lines.items() if f"poses.{k}" == exc.field), None)
            if number is None:
                raise
            raise CanonicalError(exc.status, exc.code, f"{args.poses}:{number}: {exc.message}", exc.field) from None
    print(f"session {done['id']}: {done['corrected']} poses corrected, {done['removed']} frames removed"
          + (f", {done['dropped']} not archived dropped" if done["dropped"] else "") + f"; it holds {done['frames']} frames",
          file=sys.stderr)
    if args.json:
        print(json.dumps(done))
    return 0
