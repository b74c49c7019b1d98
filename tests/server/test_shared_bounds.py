"""What all requests share is bounded: the request bodies in flight, and the event streams a fold is
sent to. On a real service process with small limits (loopback, a few connections), and the event
fan-out in process."""

from __future__ import annotations

import asyncio
import contextlib
import socket

import httpx
import pytest

from server.events import DROPPED, FoldEvents

from .harness import ServerProcess, wait_for

MiB = 1 << 20


@pytest.fixture(scope="module")
def bounded(tmp_path_factory):
    """A service whose bodies in flight hold 4 MiB (bodies of 2 MiB at most), with 2 event streams per
    session and 3 in all."""
    root = tmp_path_factory.mktemp("bounded")
    proc = ServerProcess(root / "data", root / "server.log", max_body_bytes=2 * MiB, max_inflight_body_bytes=4 * MiB,
                         max_event_streams_per_session=2, max_event_streams=3, warm_up="false",
                         snapshot_every_seconds=3600)
    proc.start()
    try:
        yield proc
    except BaseException:
        print(proc.log())
        raise
    finally:
        proc.stop()


def gauge(proc: ServerProcess, name: str) -> float:
    for line in httpx.get(f"{proc.url}/metrics").text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


def head(length: int | None) -> bytes:
    size = f"Content-Length: {length}" if length is not None else "Transfer-Encoding: chunked"
    return (f"POST /v1/sessions/none/frames HTTP/1.1\r\nHost: test\r\nContent-Type: application/msgpack\r\n"
            f"{size}\r\n\r\n").encode()


def reply_of(s: socket.socket) -> tuple[int, bytes, bytes]:
    """(status, head, body) of the answer on ``s``."""
    out = b""
    with contextlib.suppress(socket.timeout, ConnectionResetError):
        while chunk := s.recv(65536):
            out += chunk
            answer_head, sep, body = out.partition(b"\r\n\r\n")
            length = [int(line.split(b":")[1]) for line in answer_head.lower().split(b"\r\n")
                      if line.startswith(b"content-length:")]
            if sep and length and len(body) >= length[0]:
                break
    answer_head, _, body = out.partition(b"\r\n\r\n")
    return int(answer_head.split()[1]), answer_head, body


def test_bodies_in_flight_are_bounded_across_requests_and_given_back(bounded):
    slow, idle = [], []
    sent = 3 * MiB // 2 - 65536
    try:
        for _ in range(8):  # declared bodies of 2 MiB, none of it sent: they hold nothing of the 4 MiB
            s = socket.create_connection(("127.0.0.1", bounded.port), timeout=10)
            s.sendall(head(2 * MiB))
            idle.append(s)
        for _ in range(2):  # two slow uploads of 1.5 MiB: all but their last 64 KiB sent
            s = socket.create_connection(("127.0.0.1", bounded.port), timeout=10)
            s.sendall(head(3 * MiB // 2) + b"\x81" * sent)
            slow.append(s)
        assert wait_for(lambda: gauge(bounded, "canonical_request_body_bytes") == 2 * sent)
        # a third would pass the 4 MiB: refused once its bytes would, naming the setting
        with socket.create_connection(("127.0.0.1", bounded.port), timeout=10) as s:
            with contextlib.suppress(OSError):
                s.sendall(head(3 * MiB // 2) + b"\x81" * (3 * MiB // 2))
            status, answer_head, body = reply_of(s)
        assert status == 429 and b"retry-after: 1" in answer_head.lower(), answer_head
        assert b"max_inflight_body_bytes" in body
        # a chunked body is counted as it arrives: refused once it would pass them
        with socket.create_connection(("127.0.0.1", bounded.port), timeout=10) as s:
            s.sendall(head(None))
            with contextlib.suppress(OSError):
                for _ in range(16):  # 16 x 128 KiB = 2 MiB > the 1 MiB left
                    s.sendall(b"20000\r\n" + b"\x81" * 0x20000 + b"\r\n")
            status, _, body = reply_of(s)
        assert status == 429 and b"max_inflight_body_bytes" in body
        assert gauge(bounded, "canonical_request_body_bytes") == 2 * sent
        # the slow uploads complete and are answered (no such session); their bytes are given back
        for s in slow:
            s.sendall(b"\x81" * 65536)
            assert reply_of(s)[0] == 404
    finally:
        for s in slow + idle:
            s.close()
    assert wait_for(lambda: gauge(bounded, "canonical_request_body_bytes") == 0)
    r = httpx.post(f"{bounded.url}/v1/sessions/none/frames", content=b"\x81" * (2 * MiB),
                   headers={"content-type": "application/msgpack"})
    assert r.status_code == 404


def test_a_body_framed_both_ways_is_refused_before_it_is_read(bounded):
    """Content-Length beside Transfer-Encoding: chunked (h11 reads the chunks): refused, so that no body
    is counted by one framing and read by the other."""
    with socket.create_connection(("127.0.0.1", bounded.port), timeout=10) as s:
        s.sendall(head(1).replace(b"\r\n\r\n", b"\r\nTransfer-Encoding: chunked\r\n\r\n") + b"20000\r\n" + b"\x81" * 0x20000)
        status, _, body = reply_of(s)
    assert status == 400 and b'"field":"Transfer-Encoding"' in body, body
    assert wait_for(lambda: gauge(bounded, "canonical_request_body_bytes") == 0)


def test_event_streams_are_capped_per_session_and_per_service(bounded):
    a, b = (httpx.post(f"{bounded.url}/v1/sessions", json={"voxel_size": 0.01}).json()["id"] for _ in range(2))
    with contextlib.ExitStack() as stack:
        client = stack.enter_context(httpx.Client(base_url=bounded.url, timeout=10))
        readers = []  # each open stream's reader, kept: a reader collected closes its stream

        def open_stream(sid: str) -> httpx.Response:
            r = stack.enter_context(client.stream("GET", f"/v1/sessions/{sid}/events"))
            if r.status_code == 200:
                readers.append(r.iter_raw())
                assert next(readers[-1]).startswith(b"event: state")
            else:
                r.read()
            return r

        first, _ = open_stream(a), open_stream(a)
        r = open_stream(a)
        assert r.status_code == 429 and r.headers["Retry-After"]
        assert r.json()["error"]["field"] == "max_event_streams_per_session"
        assert open_stream(b).status_code == 200
        r = open_stream(b)
        assert r.status_code == 429 and r.json()["error"]["field"] == "max_event_streams"
        assert gauge(bounded, "canonical_event_streams") == 3
        first.close()  # a stream that ends gives its slot back
        assert wait_for(lambda: gauge(bounded, "canonical_event_streams") == 2)
        assert open_stream(b).status_code == 200


def test_a_subscriber_that_never_reads_is_dropped_and_never_holds_a_fold():
    async def run():
        events = FoldEvents(per_session=4, total=4, queue_size=3)
        slow, live = events.subscribe("s"), events.subscribe("s")
        received = []
        for k in range(8):  # each publish is a fold's: it returns at once, whoever reads or not
            events.publish("s", {"type": "fold", "frames": k + 1})
            received.append(live.get_nowait())
        assert len(received) == 8 and received[-1].event["frames"] == 8 and b'"frames":8' in received[-1].data
        # the slow one fell behind after its queue filled: dropped, told so, no longer sent to
        assert slow.qsize() == 1 and slow.get_nowait() is DROPPED
        assert events.subscribers("s") == 1 and events.dropped == 1
        assert events.open_streams() == 2  # its slot is held until its stream ends
        events.unsubscribe("s", slow)
        assert events.open_streams() == 1

    asyncio.run(run())
