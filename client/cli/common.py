"""What the commands share: their connection options and client, ``--json``, warnings on stderr,
and the usage error `main` prints on one line."""

from __future__ import annotations

import argparse
import contextlib
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


def connect(args) -> Client:
    """The SDK client of the service that ``--url`` and ``--token`` name."""
    return Client(args.url, token=args.token)


def add_json(p: argparse.ArgumentParser, what: str) -> None:
    """``--json``: the command prints ``what`` as JSON on stdout instead of its table or summary."""
    p.add_argument("--json", action="store_true", help=f"print {what} as JSON on stdout (for scripts)")


@contextlib.contextmanager
def warnings_on_stderr():
    """Warnings raised inside (a loader's skipped frames, say) as one line each on stderr, after it."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        yield
    for warning in caught:
        print(f"warning: {warning.message}", file=sys.stderr)
