"""The ``canonical`` command line.

    canonical serve [--host H] [--port P] [--data-dir D] [--threads N] [--cluster [--address A] [--owners N]]
    canonical stream DATASET --url URL [--session ID | [--voxel-size S] [--set PATH=VALUE ...]] [--stride K] [--max-frames N] [--scale F] [--strict] [--json]
    canonical render --url URL --session ID (--frame-like DATASET:INDEX ... | (--pose FILE | --trajectory FILE) (--K fx,fy,cx,cy --size WxH | --frame-like DATASET:INDEX)) -o out.png|'view_{i}.png'|DIR/
    canonical export --url URL --session ID -o scene.ply|scene.splat
    canonical export --url URL --session ID --mesh -o surface.ply
    canonical sessions --url URL [--json] [--prune [--dry-run]]
    canonical view --url URL --session ID [--no-browser]   (print the web viewer's URL, open a browser)
    canonical watch --url URL --session ID [--every S] [--json]   (a line per interval of folds, until it is deleted)
    canonical demo [DATASET] [--out DIR]   (start a service, stream a sample, write a render and a PLY)
    canonical eval DATASET --views 2,4,8,16 --out DIR [--methods ...] [--noise ...]
    canonical depth DATASET --out DIR [--sources 2]   (plane-sweep depth + uncertainty pictures)
    canonical train CAPTURE... --out MODEL.safetensors [--seed S] [--steps K] [--minutes M] [--device cpu|cuda]

Every subcommand is one entry of `COMMANDS`: a name mapped to (add_arguments, run), both in the
module of its group of commands (`serve`, `stream`, `render`, `sessions`, `poses`, `demo`, `offline`).
To add one, write both functions there and register them here:
``COMMANDS["demo"] = Command(demo.add_demo, demo.run_demo, "...")``. What several commands share is in
`common`; `capture` reads a capture's frames for ``stream`` and ``demo``, `launch` starts a service
as a child process. The CLI talks to the service over HTTP (`client.sdk`); ``serve`` (which runs it
under uvicorn) and ``repair`` (which works on a stopped service's data directory) import it where
they run, so the package itself imports nothing from ``server``. Datasets are read client-side with
canonical_core.datasets.

For scripts, the commands that talk to a service print their result alone on stdout: ``stream`` the
session's id (``S=$(canonical stream ...)``), ``render`` and ``export`` the paths they wrote, one a
line, ``view`` the page's URL, ``watch`` a line per event (``--json``: an object per event), ``sessions`` its table (``--prune``: a line per removed session); ``--json`` (stream, sessions, poses) prints a
JSON result instead. Progress, warnings and summaries go to stderr.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import Callable

import httpx

from ..sdk import CanonicalError, ServiceUnreachable
from . import demo, offline, poses, render, serve, sessions, stream
from .common import UsageError


@dataclass(frozen=True)
class Command:
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    help: str


COMMANDS: dict[str, Command] = {
    "serve": Command(serve.add_serve, serve.run_serve, "run the service (uvicorn)"),
    "stream": Command(stream.add_stream, stream.run_stream, "stream a dataset's frames into a session"),
    "repair": Command(serve.add_repair, serve.run_repair, "list or repair sessions whose files are damaged (service stopped)"),
    "render": Command(render.add_render, render.run_render, "render a session at a camera to a PNG"),
    "export": Command(render.add_export, render.run_export, "download a session's Gaussians as .ply or .splat, or with --mesh its surface mesh"),
    "sessions": Command(sessions.add_sessions, sessions.run_sessions, "list sessions"),
    "view": Command(sessions.add_view, sessions.run_view, "print a session's web viewer URL and open it in a browser"),
    "watch": Command(sessions.add_watch, sessions.run_watch, "print a session's folds as they come, until it is deleted"),
    "poses": Command(poses.add_poses, poses.run_poses, "correct a session's frame poses from a pose file (a loop closure), or remove frames"),
    "demo": Command(demo.add_demo, demo.run_demo, "start a service, stream a sample capture, write a render and a PLY"),
    "depth": Command(offline.add_depth, offline.run_depth, "estimate depth + uncertainty of a dataset's frames by plane sweep, write pictures"),
    "eval": Command(offline.add_eval, offline.run_eval, "evaluate methods on held-out views of a dataset (results.json/md, plots, grids)"),
    "train": Command(offline.add_train, offline.run_train, "train the decoder's heads on RGB-D captures, write a checkpoint and a report"),
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
    except (httpx.TransportError, ServiceUnreachable) as exc:  # unreachable, refused, timed out
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
