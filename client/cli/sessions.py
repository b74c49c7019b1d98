"""``sessions`` (the service's sessions as a table or JSON; ``--prune`` applies its retention policy),
``view`` (a session's web viewer page) and ``watch`` (a session's folds as they come, in a terminal)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from ..sdk.session import path_segment
from .common import UsageError, add_connection, add_json, connect, seconds_arg, session_id


# -- sessions -----------------------------------------------------------------------------------
def add_sessions(p: argparse.ArgumentParser) -> None:
    add_connection(p)
    add_json(p, "the sessions (the service's summaries, and each one's age_s and idle_s in seconds); with --prune "
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
        raise UsageError("--dry-run goes with --prune")
    if args.prune:
        return run_prune(args)
    with connect(args) as client:
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
    for s in sessions:  # what an operator has to do about a session not served, under the table
        if s.get("problem"):
            print(f"{s['id']}: {s['problem']}")
    return 0


def run_prune(args) -> int:
    """``sessions --prune``: the removed sessions on stdout (one a line), the summary on stderr."""
    with connect(args) as client:
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
    add_connection(p)
    p.add_argument("--session", type=session_id, required=True, help="session id")
    p.add_argument("--no-browser", action="store_true", help="only print the URL")


def viewer_url(base: str, session_id: str) -> str:
    """The web viewer's page of a session (the token never goes into it: the page asks for it)."""
    return f"{base.rstrip('/')}/sessions/{path_segment(session_id, 'session_id')}/view"


def has_display() -> bool:
    """Whether a graphical browser can open here (a console browser would take over the terminal)."""
    return sys.platform in ("darwin", "win32") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def run_view(args) -> int:
    with connect(args) as client:
        client.session(args.session)  # 404 for an unknown id, 401 for a missing token: said before any URL
    url = viewer_url(args.url, args.session)
    print(url)
    if args.token or os.environ.get("CANONICAL_API_TOKEN"):
        print("the page asks for the API token once (kept in the browser tab, sent as a bearer header)", file=sys.stderr)
    if not args.no_browser and has_display():
        import webbrowser

        webbrowser.open(url)
    return 0


# -- watch ------------------------------------------------------------------------------------------
def add_watch(p: argparse.ArgumentParser) -> None:
    add_connection(p)
    p.add_argument("--session", type=session_id, required=True, help="session id")
    p.add_argument("--every", type=seconds_arg, default=1.0, help=(
        "seconds: at most one line per interval, standing for the folds since the last (default 1; 0: a line "
        "for every fold)"))
    add_json(p, "each event (its name and fields, one JSON object a line)")


def watch_line(name: str, event: dict) -> str:
    """One event of a session's stream for people: ``fold`` as its counts and the latest warnings."""
    def counts(e: dict) -> str:
        return f"{e['frames']} frame{'' if e['frames'] == 1 else 's'}, {e['voxels']} voxels"

    if name == "state":
        return f"{counts(event)}: waiting for folds"
    if name == "deleted":
        return f"session {event['id']} deleted"
    if name != "fold":
        return f"{name}: {json.dumps(event)}"
    folds = event.get("folds", 1)
    text = f"frame {event['report']['frame_index']}: {counts(event)}" + (f" ({folds} folds)" if folds > 1 else "")
    # a batched event names the latest warning among its folds; a fold's own event, its report's
    warned = event.get("warned") if "warned" in event else (event["report"] if event["report"].get("warnings") else None)
    if warned:
        text += f"; frame {warned['frame_index']}: {' · '.join(warned['warnings'])}"
    return text


def run_watch(args) -> int:
    """Print the session's events until it is deleted (exit 0), or the stream falls behind or the
    service ends it (it stopped, or restarted: exit 1); Ctrl-C stops it."""
    with connect(args) as client:
        try:
            for name, event in client.session(args.session).events(every=args.every or None):
                print(json.dumps({"event": name, **event}) if args.json else watch_line(name, event), flush=True)
                if name == "dropped":
                    print("error: the stream fell behind (this terminal read too slowly); run watch again",
                          file=sys.stderr)
                    return 1
                if name == "deleted":
                    return 0
        except KeyboardInterrupt:
            return 0
    print("error: the service ended the stream (it stopped or restarted); run watch again", file=sys.stderr)
    return 1
