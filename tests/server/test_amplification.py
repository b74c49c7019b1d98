"""Small requests that would make large objects, on a real server: array maps whose declared shapes
are gigabytes, msgpack of empty lists, JSON bodies of invalid items, and numbered frames read ahead
of their turn. Each is refused before it costs what it declares, and the service's resident memory
stays within tens of megabytes of where it was."""

from __future__ import annotations

import json
import socket
import threading
import time

import httpx
import msgpack
import numpy as np
import pytest
import zstandard

from server.ordering import MAX_AHEAD

from .harness import VOXEL, ServerProcess, msgpack_frame, resident_mib, small_frames

MSGPACK = {"Content-Type": "application/msgpack"}
WAIT_S = 3.0
GROWTH_MIB = 150  # far below what each request declares (gigabytes); a fold of a small frame stays under it


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("amplification")
    proc = ServerProcess(root / "data", root / "server.log", frame_order_wait_s=WAIT_S, snapshot_every_seconds=3600,
                         warm_up="false")
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def sid(service, frames):
    session_id = httpx.post(f"{service.url}/v1/sessions", json={"voxel_size": VOXEL}).json()["id"]
    assert post(service, session_id, msgpack.packb(msgpack_frame(frames[0]), use_bin_type=True)).status_code == 200
    return session_id


def post(service, session_id: str, body: bytes, **headers) -> httpx.Response:
    return httpx.post(f"{service.url}/v1/sessions/{session_id}/frames", content=body, headers={**MSGPACK, **headers},
                      timeout=60)


def zstd_of_zeros(nbytes: int) -> bytes:
    """A zstandard frame of ``nbytes`` zeros that does not declare its size: kilobytes on the wire."""
    out = zstandard.ZstdCompressor(write_content_size=False).compressobj()
    chunk = bytes(1 << 20)
    data = b"".join(out.compress(chunk) for _ in range(nbytes >> 20))
    return data + out.flush()


def bomb(shape: list[int], dtype: str, nbytes: int) -> dict:
    return {"dtype": dtype, "shape": shape, "data": zstd_of_zeros(nbytes), "codec": "zstd"}


@pytest.mark.parametrize("field, array, status", [
    ("rgb", bomb([1, 1, 600 << 20], "uint8", 600 << 20), 422),  # a pixel of 600 million channels
    ("K", bomb([8192, 8192], "float32", 256 << 20), 422),  # an 8192 x 8192 "matrix"
    ("c2w", bomb([8192, 8192], "float32", 256 << 20), 422),
    ("depth", bomb([1 << 30, 1 << 30], "float32", 1 << 20), 413),  # was a MemoryError: a 500
], ids=["rgb-channels", "K", "c2w", "depth-sides"])
def test_array_maps_declaring_gigabytes_are_refused_before_their_bytes_are_read(service, sid, frames, field, array, status):
    message = {**msgpack_frame(frames[1]), field: array}
    before = resident_mib(service.proc.pid, peak=True)
    r = post(service, sid, msgpack.packb(message, use_bin_type=True))
    assert r.status_code == status, r.text
    assert r.json()["error"]["field"] == field
    assert resident_mib(service.proc.pid, peak=True) - before < GROWTH_MIB
    assert httpx.get(f"{service.url}/v1/sessions/{sid}").json()["frames"] == 1


@pytest.mark.parametrize("body", [msgpack.packb([[]] * 2_000_000), msgpack.packb({"rgb": [[[[]] * 60] * 60] * 60}),
                                  msgpack.packb({"frame_id": "x" * (2 << 20)})], ids=["list", "nested", "string"])
def test_msgpack_that_would_make_millions_of_objects_is_malformed_at_once(service, sid, body):
    before = resident_mib(service.proc.pid, peak=True)
    r = post(service, sid, body)
    assert r.status_code == 400 and r.json()["error"]["code"] == "malformed_body", r.text
    assert resident_mib(service.proc.pid, peak=True) - before < GROWTH_MIB


def test_a_json_body_of_invalid_items_is_one_error_and_json_bodies_are_bounded(service, sid):
    """Parsed and validated, 3.3 MB of empty lists are about 300 MB at the peak, one body at a time on
    the event loop (the JSON bound keeps that so); an error object for each invalid item made it a
    gigabyte more, and a 60 MB body ended in the kernel's OOM killer."""
    before = resident_mib(service.proc.pid, peak=True)
    items = json.dumps({"remove": [[]] * 1_100_000}, separators=(",", ":")).encode()
    r = httpx.post(f"{service.url}/v1/sessions/{sid}/poses", content=items, headers={"Content-Type": "application/json"},
                   timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == "remove", r.text
    assert "at most 1000000" in r.json()["error"]["message"]  # one error, not one per item
    assert resident_mib(service.proc.pid, peak=True) - before < 400
    limits = httpx.get(f"{service.url}/v1/limits").json()
    over = b" " * (limits["max_json_body_bytes"] + 1)
    for headers in ({"Content-Type": "application/json"}, {}):  # a body without a type is parsed as JSON too
        r = httpx.post(f"{service.url}/v1/sessions/{sid}/render", content=over, headers=headers, timeout=60)
        assert r.status_code == 413 and "max_json_body_bytes" in r.json()["error"]["message"], r.text
    assert httpx.get(f"{service.url}/v1/sessions/{sid}").json()["frames"] == 1


def test_numbered_frames_read_ahead_of_their_turn_are_bounded(service, frames):
    """Frames numbered far past the session's count wait, each holding its decoded arrays: past
    `MAX_AHEAD` of them a frame gets 429 (sent again later; not a refusal), and the waiting ones are
    refused once no frame comes for the wait."""
    session_id = httpx.post(f"{service.url}/v1/sessions", json={"voxel_size": VOXEL}).json()["id"]
    body = msgpack.packb(msgpack_frame(frames[1]), use_bin_type=True)
    answers: dict[int, httpx.Response] = {}

    def send(k: int):
        answers[k] = post(service, session_id, body, **{"Frame-Index": str(1000 + k)})

    threads = [threading.Thread(target=send, args=(k,)) for k in range(MAX_AHEAD + 4)]
    for t in threads:  # one after another, each read before the next comes (well within the wait)
        t.start()
        time.sleep(0.1)
    for t in threads:
        t.join()
    ahead = [r for r in answers.values() if r.status_code == 429 and "read ahead" in r.json()["error"]["message"]]
    assert ahead and all(r.json()["error"]["field"] == "Frame-Index" and r.headers["Retry-After"] == "1" for r in ahead)
    assert all(r.status_code in (409, 429) for r in answers.values())
    assert httpx.get(f"{service.url}/v1/sessions/{session_id}").json()["frames"] == 0


def test_a_client_that_never_reads_its_large_answer_is_let_go(tmp_path, frames):
    """A render of 2000x1500 in msgpack (about 40 MB) asked for and never read: the service sends it a
    piece at a time, each within send_timeout_s, then closes the connection, and its bytes go back;
    before, it held them for as long as the connection stayed open."""
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", send_timeout_s=1, warm_up="false",
                         snapshot_every_seconds=3600).start()
    try:
        session_id = httpx.post(f"{proc.url}/v1/sessions", json={"voxel_size": VOXEL}).json()["id"]
        assert post(proc, session_id, msgpack.packb(msgpack_frame(frames[0]), use_bin_type=True)).status_code == 200
        K = frames[0]["K"] * [[2000 / 320], [1500 / 240], [1]]
        view = json.dumps({"K": K.tolist(), "c2w": frames[0]["c2w"].tolist(), "width": 2000, "height": 1500}).encode()
        with socket.create_connection(("127.0.0.1", proc.port), timeout=30) as s:
            s.sendall(b"POST /v1/sessions/%s/render HTTP/1.1\r\nHost: x\r\nAccept: application/msgpack\r\n"
                      b"Content-Type: application/json\r\nContent-Length: %d\r\n\r\n%s" % (session_id.encode(), len(view), view))
            time.sleep(6)  # reads nothing meanwhile
            got = b""
            while chunk := s.recv(1 << 20):
                got += chunk
        head, _, body = got.partition(b"\r\n\r\n")
        length = int(next(line.split(b":")[1] for line in head.lower().split(b"\r\n") if line.startswith(b"content-length")))
        assert head.startswith(b"HTTP/1.1 200") and len(body) < length  # closed before the whole answer
        assert "took no bytes of its answer for 1 s (send_timeout_s)" in proc.log()
    finally:
        proc.stop()


def test_a_reader_that_stalls_in_a_streamed_answer_of_small_pieces_is_let_go():
    """A streamed export goes out in blocks (a .splat's are half a MiB): each is sent within
    send_timeout_s as a large answer's pieces are, so a client that stops reading lets go of the
    blocks still to come and the Gaussians behind them."""
    import asyncio

    from starlette.responses import StreamingResponse

    from server.app import BodyBytes, GuardMiddleware
    from server.metrics import Metrics
    from server.settings import Settings

    made = []

    def blocks():  # endless blocks of 512 KiB, as long as anyone takes them
        while True:
            made.append(1)
            yield bytes(1 << 19)

    async def app(scope, receive, send):
        await StreamingResponse(blocks(), media_type="application/octet-stream")(scope, receive, send)

    async def scenario():
        guard = GuardMiddleware(app, Settings(send_timeout_s=0.5), Metrics(), BodyBytes(1 << 30))
        taken = []

        async def send(message):  # takes the head and one piece of the first block, then nothing more
            if message["type"] == "http.response.body":
                if taken:
                    await asyncio.Event().wait()
                taken.append(len(message["body"]))

        async def receive():
            await asyncio.Event().wait()

        scope = {"type": "http", "method": "GET", "path": "/x", "headers": [], "query_string": b""}
        await asyncio.wait_for(guard(scope, receive, send), 10)  # let go (ReaderStalled), not held
        return taken

    from server.app import SEND_PIECE_BYTES

    assert asyncio.run(scenario()) == [SEND_PIECE_BYTES] and len(made) <= 3


def test_the_next_frame_is_taken_whatever_waits_ahead_of_it(tmp_path, shelf_dir):
    """`MAX_AHEAD` frames numbered after a gap wait; the frame that fills the gap is still taken (were it
    refused, they would all wait in vain), and then every one of them folds in its place. (A service of
    its own, whose frames wait long enough for the folds of a loaded machine.)"""
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", warm_up="false", snapshot_every_seconds=3600).start()
    try:
        _frames_ahead_then_the_next(proc, small_frames(shelf_dir, count=MAX_AHEAD + 1, step=2))
    finally:
        proc.stop()


def _frames_ahead_then_the_next(service, frames):
    session_id = httpx.post(f"{service.url}/v1/sessions", json={"voxel_size": VOXEL}).json()["id"]
    answers: dict[int, httpx.Response] = {}

    def send(k: int):
        body = msgpack.packb(msgpack_frame(frames[k]), use_bin_type=True)
        deadline = time.monotonic() + 60
        # sent again after a 429, as a client does (a loaded machine's decodes can fill the ingest queue)
        while (r := post(service, session_id, body, **{"Frame-Index": str(k)})).status_code == 429 \
                and time.monotonic() < deadline:
            time.sleep(float(r.headers["Retry-After"]))
        answers[k] = r

    threads = [threading.Thread(target=send, args=(k,)) for k in range(1, MAX_AHEAD + 1)]
    for t in threads:  # each read before the next comes, well within the wait
        t.start()
        time.sleep(0.1)
    send(0)
    for t in threads:
        t.join()
    assert {k: r.status_code for k, r in answers.items()} == {k: 200 for k in range(MAX_AHEAD + 1)}, answers[0].text
    assert httpx.get(f"{service.url}/v1/sessions/{session_id}").json()["frames"] == MAX_AHEAD + 1
