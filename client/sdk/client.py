"""`Client`: a connection to the service (its URL and token, 429s retried, errors as `CanonicalError`),
its sessions, limits, health and metrics."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from typing import TypeVar

import httpx
import numpy as np

from .errors import CanonicalError, ServiceUnreachable
from .session import Session, path_segment

T = TypeVar("T")


# answers that say the service (or a proxy before it) could not take the request now, not that the
# request is wrong: the service itself answers a bad request 4xx, and never 500 by design
RETRIED_SERVER_ERRORS = frozenset({500, 502, 503, 504})


def default_url() -> str:
    """The service's base URL when none is given: ``CANONICAL_URL`` from the environment, else the
    address `canonical serve` listens on by default."""
    return os.environ.get("CANONICAL_URL") or "http://127.0.0.1:8000"


def _setting(value, name: str):
    """A session setting as JSON carries it: numpy scalars and arrays as Python numbers and lists;
    ValueError naming the setting (``range.near``) where it holds a NaN or an infinity, which JSON
    cannot carry (the service would never see it to name it)."""
    if isinstance(value, dict):
        return {key: _setting(item, f"{name}.{key}") for key, item in value.items()}
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [_setting(item, name) for item in value]
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return value


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Client:
    """A connection to the service.

    Args:
        url: base URL, e.g. ``http://127.0.0.1:8000`` (default: `default_url`, as the CLI's ``--url``,
            so that scripts and the CLI find the same service).
        token: bearer token (default: ``CANONICAL_API_TOKEN`` from the environment, if set).
        timeout: seconds per request (None: no limit).
        max_retries: how often a 429 is retried (waiting its Retry-After, at most ``max_wait`` s each);
            a request the service takes once however often it comes (every GET, a view, a frame with a
            ``frame_id``: the service folds one id once) is also retried this often, with growing waits,
            when the service cannot be reached or answers 500, 502, 503 or 504 (a restart, a proxy whose
            backend died): about half a minute in all with the defaults. A client that has never reached
            the service is not kept waiting: a refused connection is `ServiceUnreachable` at once (a
            wrong URL, or a service not started).
    """

    def __init__(self, url: str | None = None, token: str | None = None, timeout: float | None = 120.0,
                 max_retries: int = 8, max_wait: float = 10.0):
        if isinstance(max_retries, bool) or not isinstance(max_retries, int) or max_retries < 0:
            raise ValueError(f"max_retries: expected a whole number of at least 0, got {max_retries!r}")
        if timeout is not None and not (_number(timeout) and 0 < timeout < math.inf):
            raise ValueError(f"timeout: expected seconds above 0 (or None: no limit), got {timeout!r}")
        if not (_number(max_wait) and 0 <= max_wait < math.inf):
            raise ValueError(f"max_wait: expected seconds, 0 or more, got {max_wait!r}")
        url = url if url is not None else default_url()
        try:
            scheme = httpx.URL(url).scheme if isinstance(url, str) else None
        except httpx.InvalidURL:
            scheme = None
        if scheme not in ("http", "https"):
            raise ValueError(f"url: expected the service's http:// or https:// address, got {url!r}")
        token = token if token is not None else os.environ.get("CANONICAL_API_TOKEN") or None
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.max_retries, self.max_wait = max_retries, max_wait
        self._limits: dict | None = None
        self._reached = False  # whether the service ever answered this client

    def _request(self, method: str, path: str, idempotent: bool = False, stream: bool = False, **kwargs) -> httpx.Response:
        """``method`` on ``path``, 429s retried; with ``idempotent`` (a request the service takes once
        however often it comes: every GET, a view, a frame with its ``frame_id``), failures to reach
        the service and `RETRIED_SERVER_ERRORS` too. `ServiceUnreachable` when no answer came. With
        ``stream``, a successful answer's body is left to the caller to read (`_download`)."""
        idempotent = idempotent or method == "GET"
        for attempt in range(self.max_retries + 1):
            try:
                r = self._http.send(self._http.build_request(method, path, **kwargs), stream=stream)
            except httpx.TransportError as exc:
                never = not self._reached and isinstance(exc, httpx.ConnectError)  # nothing listens there
                if not idempotent or attempt == self.max_retries or never:
                    raise self._unreachable(method, path, exc) from exc
                time.sleep(self._retry_after(None, attempt))
                continue
            self._reached = True
            again = r.status_code == 429 or (idempotent and r.status_code in RETRIED_SERVER_ERRORS)
            if not again or attempt == self.max_retries:
                break
            r.close()
            time.sleep(self._retry_after(r, attempt))
        if r.status_code >= 400:
            try:
                r.read()
            except httpx.TransportError as exc:  # the error answer cut short: no answer to tell
                raise self._unreachable(method, path, exc) from exc
            finally:
                r.close()
            raise self._error(r)
        return r

    def _download(self, path: str, write: Callable[[Iterator[bytes]], T], **kwargs) -> T:
        """``write(chunks)`` of the body of a GET of ``path`` as it arrives (a file of hundreds of MB
        never all in memory). The request is made, and retried as `_request` does, before ``write`` is
        called, so a refusal is raised before the caller makes any file; a connection that fails on
        the way is retried from the start (``write`` is called again: it must begin afresh), and is
        `ServiceUnreachable` after the last retry. The answer is closed however ``write`` ends."""
        attempt = 0
        while True:
            r = self._request("GET", path, stream=True, **kwargs)
            try:
                return write(self._body(r, path))
            except ServiceUnreachable:
                if attempt == self.max_retries:
                    raise
            finally:
                r.close()
            time.sleep(self._retry_after(None, attempt))
            attempt += 1

    def _body(self, r: httpx.Response, path: str) -> Iterator[bytes]:
        try:
            yield from r.iter_bytes()
        except httpx.TransportError as exc:
            raise self._unreachable("GET", path, exc) from exc

    def _unreachable(self, method: str, path: str, exc: Exception) -> ServiceUnreachable:
        return ServiceUnreachable(f"{method} {self._http.base_url}{path}: {type(exc).__name__}: {exc or 'no answer'}")

    def _retry_after(self, r: httpx.Response | None, attempt: int) -> float:
        """Seconds before retry ``attempt``: the answer's Retry-After, else (no answer, or none in it)
        a wait that doubles with each attempt; at most ``max_wait``."""
        try:
            wait = float(r.headers.get("Retry-After", "") if r is not None else "")
        except ValueError:
            wait = 0.25 * 2**attempt
        return min(self.max_wait, wait if math.isfinite(wait) and wait >= 0 else 1.0)

    @staticmethod
    def _error(r: httpx.Response) -> CanonicalError:
        """The service's error answer (``{"error": {"code", "message", "field"}}``), or one with the body's
        text where another server (a proxy) answered otherwise."""
        try:
            err = r.json()["error"]
            return CanonicalError(r.status_code, str(err.get("code", "error")), str(err.get("message", "")),
                                  err.get("field"))
        except (ValueError, KeyError, TypeError, AttributeError):
            return CanonicalError(r.status_code, "error", r.text[:500])

    def create_session(self, voxel_size: float | None = None, **settings) -> Session:
        """A new session; ``settings`` are the service's session settings (SceneConfig's public fields:
        max_voxels, sh_degree, ..., groups as dicts, e.g. ``range={"near": 0.2}, sensor={"family": "hololens"}``).
        Without ``voxel_size`` the service chooses it from the first frame with depth (its stats say which)."""
        body = settings if voxel_size is None else {"voxel_size": voxel_size, **settings}
        body = {name: _setting(value, name) for name, value in body.items()}
        r = self._request("POST", "/v1/sessions", json=body)
        return Session(self, r.json()["id"], label_dim=0)

    def session(self, session_id: str) -> Session:
        """An existing session (checked: raises CanonicalError 404 when unknown, ValueError naming
        session_id when it is empty)."""
        stats = self._request("GET", f"/v1/sessions/{path_segment(session_id, 'session_id')}").json()
        return Session(self, session_id, label_dim=stats.get("label_dim"))

    def limits(self) -> dict:
        """The service's request limits (``GET /v1/limits``: ``max_rgb_only_pixels``, ``max_image_pixels``,
        ...), read once per client; {} from a service that does not publish them."""
        if self._limits is None:
            try:
                self._limits = self._request("GET", "/v1/limits").json()
            except CanonicalError as exc:
                if exc.status != 404:
                    raise
                self._limits = {}
        return self._limits

    def sessions(self) -> list[dict]:
        """Every session's summary (``GET /v1/sessions``: id, frames, voxels, ...), oldest first."""
        return self._request("GET", "/v1/sessions").json()["sessions"]

    def prune_sessions(self, dry_run: bool = False) -> dict:
        """Apply the service's retention policy now (``POST /v1/sessions/prune``); with ``dry_run`` only
        list what it would remove. Returns its report (``removed``: the sessions, oldest first)."""
        return self._request("POST", "/v1/sessions/prune", params={"dry_run": "true" if dry_run else "false"}).json()

    def health(self) -> dict:
        """The service's health (``GET /healthz``)."""
        return self._request("GET", "/healthz").json()

    def metrics(self) -> str:
        """The service's metrics in Prometheus' text format (``GET /metrics``)."""
        return self._request("GET", "/metrics").text

    def close(self) -> None:
        """Close the client's connections (also on leaving a ``with Client(...)`` block)."""
        self._http.close()

    def __repr__(self) -> str:
        return f"Client({str(self._http.base_url)!r})"

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
