"""``serve`` (the service in this process, under uvicorn or on Ray Serve) and ``repair`` (a stopped
service's data directory). The one module that imports the service's code, only where a command runs it."""

from __future__ import annotations

import argparse
import os
import sys

from .common import UsageError, session_id


# -- serve --------------------------------------------------------------------------------------
LOG_LEVELS = ("critical", "error", "warning", "info", "debug", "trace")  # uvicorn's (uvicorn.config.LOG_LEVELS)


def add_serve(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default=None, help="bind address (default: $CANONICAL_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="port (default: $CANONICAL_PORT or 8000)")
    p.add_argument("--data-dir", default=None, help="session storage (default: $CANONICAL_DATA_DIR or ./data)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads per job (default: $CANONICAL_THREADS or all)")
    p.add_argument("--log-level", default="info", type=str.lower, choices=LOG_LEVELS,
                   help="uvicorn's log level (default: info)")
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
    _check_port(args, settings.host, settings.port)
    if args.cluster:
        try:  # the driver's node mounts the data directory as every node does: a wrong one is one line here
            _probe_folder(settings.data_dir)
        except OSError as exc:
            print(f"error: {_setting_source(args, 'data_dir')}: cannot create {exc.filename or settings.data_dir}: "
                  f"{exc.strerror or exc}", file=sys.stderr)
            return 1
        _check_ray_address(args.address)
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
    _service_logging(args.log_level)
    # The protocol closes connections whose request head is late (slowloris); bodies get 408 in the app.
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=args.log_level,
                http="server.protocol:HeadTimeoutH11Protocol", timeout_keep_alive=5)
    return 0


def _service_logging(level: str) -> None:
    """The service's own lines (its ``canonical.*`` loggers: start-up, restores, retention) on stderr
    at ``--log-level``, as uvicorn writes its own; without a handler only warnings came out, bare."""
    import logging

    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s:     %(name)s: %(message)s"))
    logger = logging.getLogger("canonical")
    logger.addHandler(handler)
    logger.setLevel("DEBUG" if level == "trace" else level.upper())
    logger.propagate = False


def _probe_folder(path) -> None:
    """OSError where the folder ``path`` cannot be made; the folders made to find out are removed again
    (a start refused later, its claims not fitting say, leaves nothing behind)."""
    from pathlib import Path

    path = Path(path).absolute()
    missing = [p for p in (path, *path.parents) if not p.exists()]
    path.mkdir(parents=True, exist_ok=True)
    for folder in missing:  # the deepest first
        folder.rmdir()


def _check_port(args, host: str, port: int) -> None:
    """UsageError naming the port's option when another process listens there already, or the host's
    when no address of this machine has that name, before the service starts anything (uvicorn, or Ray,
    would say so only after a start-up and in many lines)."""
    import errno
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        # as the servers bind: a closed socket's TIME_WAIT owns no port
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:  # a name that resolves to nothing, or to no address of this machine: the host's
            unknown = isinstance(exc, socket.gaierror) or exc.errno == errno.EADDRNOTAVAIL
            raise UsageError(f"{_setting_source(args, 'host' if unknown else 'port')}: cannot listen on {host}:{port}: "
                             f"{exc.strerror or exc}") from None


def _check_ray_address(address: str | None) -> None:
    """UsageError naming --address (or RAY_ADDRESS) when nothing answers at the Ray cluster's address,
    before Ray is asked to join it (it would retry for minutes in many lines). "auto" and "local" are
    Ray's to resolve."""
    import socket
    from urllib.parse import urlsplit

    source = "--address" if address else "RAY_ADDRESS"
    address = address or os.environ.get("RAY_ADDRESS", "")
    if address in ("", "auto", "local"):
        return
    # host:port (the head's GCS, port 6379 by default) or ray://host:port (Ray Client, 10001)
    client = address.startswith("ray://")
    try:
        where = urlsplit(address if "://" in address else f"gcs://{address}")
        host, port = where.hostname, where.port or (10001 if client else 6379)
    except ValueError as exc:
        raise UsageError(f"{source}: {address!r} is not HOST:PORT or ray://HOST:PORT ({exc})") from None
    if not host:
        raise UsageError(f"{source}: {address!r} is not HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host, port), timeout=5).close()
    except OSError as exc:
        raise UsageError(f"{source}: no Ray cluster answers at {host}:{port}: {exc.strerror or exc}") from None


def _setting_source(args, name: str) -> str:
    """Where a service setting came from: its ``serve`` option, else its CANONICAL_* variable."""
    given = name in SERVE_SETTINGS and getattr(args, name, None) is not None
    return f"--{name.replace('_', '-')}" if given else f"CANONICAL_{name.upper()}"


SECRET_SETTINGS = ("api_token",)  # their values are never printed
OTHER_VARIABLES = {"CANONICAL_URL", "CANONICAL_NODE"}  # the clients' service, a cluster node's name


def _warn_unknown_variables(settings: set[str]) -> None:
    """A warning on stderr for each CANONICAL_* variable that is no setting (a misspelt one would be
    ignored without a word), naming the setting it most resembles."""
    import difflib

    known = settings | OTHER_VARIABLES
    for name in sorted(n for n in os.environ if n.startswith("CANONICAL_") and n not in known):
        close = difflib.get_close_matches(name, sorted(known), 1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        print(f"warning: {name} is not a setting of the service{hint}; ignored", file=sys.stderr)


def serve_settings(args):
    """The service's settings (`server.settings.Settings`, or the cluster's) from the environment that
    `run_serve` filled; UsageError naming the option or variable of the first invalid one."""
    from pydantic import ValidationError

    from server.cluster.settings import ClusterSettings  # pydantic only: no Ray
    from server.settings import Settings

    kind = ClusterSettings if args.cluster else Settings
    _warn_unknown_variables({f"CANONICAL_{name.upper()}" for name in ClusterSettings.model_fields})  # either's
    try:
        return kind()
    except ValidationError as exc:
        first = exc.errors()[0]
        name = str(first["loc"][0]) if first["loc"] else "settings"
        message = first["msg"].removeprefix("Value error, ")
        given = "" if name in SECRET_SETTINGS or not first["loc"] else f", got {first['input']}"  # never a secret
        raise UsageError(f"{_setting_source(args, name)}: {message[:1].lower()}{message[1:]}{given}") from None


# -- repair -------------------------------------------------------------------------------------
def add_repair(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", default=None, help="the service's data directory (default: $CANONICAL_DATA_DIR or "
                                                    "./data); the service must be stopped")
    p.add_argument("--session", type=session_id, default=None, help="the session to repair (default: list the sessions that need it)")
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
    listing = args.session is None
    try:
        if listing:  # opened as a start opens it (which cuts torn tails and restores logs from the archive)
            store.open()
            for name, problem in sorted(store.unavailable.items()):
                print(f"{name}: {problem}")
            print(f"{len(store.unavailable)} of {len(store) + len(store.unavailable)} sessions need repair")
        else:
            print(store.repair(args.session, args.action))
    except (DataDirLocked, Unrestorable, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    finally:
        store.close(snapshot=not listing)  # a listing writes no snapshot of every session
    return 0
