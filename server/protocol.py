"""The HTTP/1.1 protocol the service runs under uvicorn: h11 with a deadline for the request head.

uvicorn closes idle keep-alive connections, but a connection that sends its request line and
headers a byte at a time (slowloris) is held open forever, one file descriptor and one parser each.
Here every request head must be complete within ``header_timeout_s`` of the connection opening or
of the previous response; otherwise the connection is closed. Slow bodies are the ASGI middleware's
job (`server.app.GuardMiddleware`, 408).

Run with ``uvicorn --http server.protocol:HeadTimeoutH11Protocol`` (``canonical serve`` does).
"""

from __future__ import annotations

import asyncio

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

from .settings import Settings


class HeadTimeoutH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, closing connections whose request head is late."""

    header_timeout_s: float | None = None  # None: read from Settings (CANONICAL_HEADER_TIMEOUT_S) on first use

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm_head_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        if type(self).header_timeout_s is None:
            type(self).header_timeout_s = Settings().header_timeout_s
        self._head_timer = self.loop.call_later(type(self).header_timeout_s, self._head_timeout)

    def _cancel_head_timer(self) -> None:
        timer = getattr(self, "_head_timer", None)
        if timer is not None:
            timer.cancel()
            self._head_timer = None

    def _head_timeout(self) -> None:
        self._head_timer = None
        # IDLE: no complete request head since the timer was armed (a request in progress is past it)
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            self.logger.info("closing a connection whose request head did not arrive in %g s", self.header_timeout_s)
            self.transport.close()
