"""Calling an ASGI app with one whole request and collecting its whole response: how an owner runs a
forwarded request through the service's own FastAPI app (routes, errors and auth unchanged)."""

from __future__ import annotations

import asyncio


async def call_app(app, method: str, path: str, query: bytes, headers: list, body: bytes) -> tuple[int, list, bytes]:
    """Run one HTTP request: ``headers`` [(name, value)] as bytes pairs. Returns (status, headers, body)."""
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "scheme": "http",
             "path": path, "raw_path": path.encode(), "root_path": "", "query_string": query,
             "headers": [(bytes(k), bytes(v)) for k, v in headers], "client": ("127.0.0.1", 0), "server": ("owner", 0)}
    done = asyncio.Event()
    delivered = False
    status, out_headers, chunks = 500, [], []

    async def receive():
        nonlocal delivered
        if not delivered:
            delivered = True
            return {"type": "http.request", "body": body, "more_body": False}
        await done.wait()  # the caller stays connected until the response is complete
        return {"type": "http.disconnect"}

    async def send(message):
        nonlocal status, out_headers
        if message["type"] == "http.response.start":
            status, out_headers = message["status"], [(bytes(k), bytes(v)) for k, v in message.get("headers", [])]
        elif message["type"] == "http.response.body":
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                done.set()

    try:
        await app(scope, receive, send)
    finally:
        done.set()
    return status, out_headers, b"".join(chunks)


async def read_body(receive) -> bytes | None:
    """A request's whole body, or None when the client disconnected."""
    chunks = []
    while True:
        message = await receive()
        if message["type"] != "http.request":
            return None
        chunks.append(message.get("body", b""))
        if not message.get("more_body", False):
            return b"".join(chunks)


async def send_response(send, status: int, headers: list, body: bytes) -> None:
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body, "more_body": False})
