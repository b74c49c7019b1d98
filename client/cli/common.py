"""What the commands share: their connection options and client, the types of their arguments,
``--json``, warnings on stderr, output errors that name the option, and the usage error `main`
prints on one line."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import warnings

from ..sdk import Client, default_url


class UsageError(Exception):
    """An option's value that cannot work whatever the files or the service hold; the message names
    the option. `main` prints it on one line and exits with 2, as argparse does for its own errors."""


def add_connection(p: argparse.ArgumentParser) -> None:
    """``--url`` and ``--token`` of a command that talks to the service (the SDK's defaults)."""
    p.add_argument("--url", default=default_url(),
                   help="service base URL (default: $CANONICAL_URL or http://127.0.0.1:8000)")
    p.add_argument("--token", default=None, help="bearer token (default: $CANONICAL_API_TOKEN)")


def session_id(text: str) -> str:
    """A ``--session`` value: a session id, which an empty one is not (in a URL it would name the list of
    sessions, not one of them).

    Example:
        >>> session_id("5eb2f4ac")
        '5eb2f4ac'
    """
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a session id, got {text!r}")
    return text


def positive_int(text: str) -> int:
    """An argument that must be a whole number of at least 1 (a usage error otherwise).

    Example:
        >>> positive_int("3")
        3
    """
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _number(text: str) -> float:
    """``text`` as a float, NaN for what is not a number (which every range check below refuses)."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def positive_number(text: str) -> float:
    """An argument that must be a finite number above 0 (a size, a factor).

    Example:
        >>> positive_number("0.5")
        0.5
    """
    value = _number(text)
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def seconds_arg(text: str) -> float:
    """A number of seconds, at least 0.

    Example:
        >>> seconds_arg("2.5")
        2.5
    """
    seconds = _number(text)
    if not 0 <= seconds < math.inf:
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return seconds


def colour_arg(text: str) -> tuple[float, float, float]:
    """``r,g,b``, each in [0, 1].

    Example:
        >>> colour_arg("1,0.5,0")
        (1.0, 0.5, 0.0)
    """
    values = [_number(word) for word in text.split(",")]
    if len(values) != 3 or not all(0 <= v <= 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected r,g,b, each in [0, 1] (e.g. 1,1,1 for white), got {text!r}")
    return tuple(values)


def connect(args) -> Client:
    """The SDK client of the service that ``--url`` and ``--token`` name."""
    return Client(args.url, token=args.token)


def add_json(p: argparse.ArgumentParser, what: str) -> None:
    """``--json``: the command prints ``what`` as JSON on stdout instead of its table or summary."""
    p.add_argument("--json", action="store_true", help=f"print {what} as JSON on stdout (for scripts)")


# what a library warning calls a loader's argument, and the CLI's option for it
OPTION_NAMES = {"strict=True": "--strict"}


@contextlib.contextmanager
def warnings_on_stderr():
    """Warnings raised inside (a loader's skipped frames, say) as one line each on stderr, after it,
    naming the CLI's options where they name a library's arguments (`OPTION_NAMES`)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        yield
    for warning in caught:
        message = str(warning.message)
        for argument, option in OPTION_NAMES.items():
            message = message.replace(argument, option)
        print(f"warning: {message}", file=sys.stderr)


@contextlib.contextmanager
def writing(option: str, path: str | os.PathLike):
    """An OSError inside (``path`` a folder, a parent that is a file, a full disk) as one line naming
    ``option`` and ``path``, the path the user gave rather than a temporary file beside it."""
    try:
        yield
    except OSError as exc:
        if isinstance(exc, (ConnectionError, TimeoutError)):  # the service's, not the file's
            raise
        where = "" if exc.filename in (None, str(path)) else f" ({exc.filename})"
        raise OSError(f"{option}: cannot write {path}: {exc.strerror or exc}{where}") from None
