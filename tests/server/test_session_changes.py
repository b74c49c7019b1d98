"""Requests in flight when their session changes under them, on a real service: a numbered frame
(``Frame-Index``) waiting for its turn ends at once when its session is deleted, when the service
stops, when its client leaves, or when a correction removes frames (saying so); a background correction of a deleted
session stops without an error."""

from __future__ import annotations

import logging
import re
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from client.sdk import MSGPACK, Client, frame_body
from server import corrections

from .harness import VOXEL, ServerProcess, in_process_server, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]

WAIT_S = 60  # the service's frame_order_wait_s here
PROMPT_S = 10.0  # an answer within this did not wait out WAIT_S


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("session_changes")
    proc = ServerProcess(root / "data", root / "server.log", frame_order_wait_s=WAIT_S, snapshot_every_seconds=3600,
                         warm_up="false")
    proc.start()
    yield proc
    proc.kill9()


def post(url: str, session_id: str, body: bytes, index: int) -> tuple[httpx.Response, float]:
    """POST a frame with its Frame-Index: the answer and the seconds it took."""
    started = time.monotonic()
    r = httpx.post(f"{url}/v1/sessions/{session_id}/frames", content=body,
                   headers={"Content-Type": MSGPACK, "Frame-Index": str(index)}, timeout=3 * WAIT_S)
    return r, time.monotonic() - started


def held_bytes(url: str) -> int:
    """The request bodies the service holds: a frame's counts until it is answered."""
    return int(re.search(r"^canonical_request_body_bytes (\d+)", httpx.get(f"{url}/metrics").text, re.M).group(1))


def streamed(client: Client, frames: list[dict]):
    session = client.create_session(voxel_size=VOXEL)
    for kwargs in frames:
        session.add_frame(**kwargs)
    return session


def test_a_frame_waiting_for_its_turn_ends_with_404_when_its_session_is_deleted(service, frames):
    with Client(service.url) as client, ThreadPoolExecutor(1) as pool:
        session = streamed(client, frames[:1])
        body = frame_body(**frames[2])
        waiting = pool.submit(post, service.url, session.id, body, 2)  # frame 1 never comes
        assert wait_for(lambda: held_bytes(service.url) >= len(body))
        session.delete()
        r, seconds = waiting.result()
    assert r.status_code == 404 and r.json()["error"]["field"] == "session_id", r.text
    assert seconds < PROMPT_S


def test_a_frame_waiting_for_its_turn_whose_client_left_is_dropped(service, frames):
    """Its client gave up (a timeout, a killed process): it was never answered, so it is not folded when
    its turn would come, and it holds neither its body nor its place meanwhile."""
    with Client(service.url) as client:
        session = streamed(client, frames[:1])
        body = frame_body(**frames[2])
        with pytest.raises(httpx.ReadTimeout):  # frame 1 never comes while this client waits
            httpx.post(f"{service.url}/v1/sessions/{session.id}/frames", content=body,
                       headers={"Content-Type": MSGPACK, "Frame-Index": "2"}, timeout=2.0)
        assert wait_for(lambda: held_bytes(service.url) == 0, PROMPT_S)  # well before WAIT_S
        session.add_frame(**frames[1])
        time.sleep(1.0)  # where the dropped frame 2 would fold now
        assert session.stats()["frames"] == 2


def test_a_correction_that_removes_frames_refuses_the_numbered_frames_in_flight_at_once(service, frames):
    """Frames 4 and 5 wait for frame 3 when frame 1 is removed: they, and frame 3 sent after, were
    numbered for the stream before the removal; a stream numbered anew goes on."""
    with Client(service.url) as client, ThreadPoolExecutor(2) as pool:
        session = streamed(client, frames[:3])
        bodies = {k: frame_body(**frames[k]) for k in (3, 4, 5)}
        waiting = [pool.submit(post, service.url, session.id, bodies[k], k) for k in (4, 5)]
        assert wait_for(lambda: held_bytes(service.url) >= len(bodies[4]) + len(bodies[5]))
        assert session.remove_frame(frames[1]["frame_id"])["frames"] == 2
        answers = [w.result() for w in waiting] + [post(service.url, session.id, bodies[3], 3)]
        for k, (r, seconds) in zip((4, 5, 3), answers):
            error = r.json()["error"]
            assert r.status_code == 409 and error["field"] == "Frame-Index", r.text
            assert error["message"] == (f"Frame-Index: frame {k} cannot be folded in its place: a correction removed "
                                        "frames after it was numbered (the session's frame count went from 3 to 2), "
                                        "so the next one is frame 2")
            assert seconds < PROMPT_S
        assert [r["frame_index"] for r in session.add_frames(frames[3:5])] == [2, 3]
        expected = streamed(client, [frames[0], frames[2], frames[3], frames[4]]).digest()["sha256"]
        assert session.digest()["sha256"] == expected


def test_a_frame_waiting_for_its_turn_does_not_hold_a_stopping_service(tmp_path, frames):
    """SIGTERM: the frame is answered 503 (not folded: a client sends it again), and the service exits
    without waiting out frame_order_wait_s."""
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", frame_order_wait_s=WAIT_S, warm_up="false").start()
    try:
        with Client(proc.url) as client, ThreadPoolExecutor(1) as pool:
            session = streamed(client, frames[:1])
            body = frame_body(**frames[2])
            waiting = pool.submit(post, proc.url, session.id, body, 2)
            assert wait_for(lambda: held_bytes(proc.url) >= len(body))
            proc.proc.terminate()
            r, seconds = waiting.result()
        assert r.status_code == 503 and r.json()["error"]["field"] == "Frame-Index", r.text
        assert seconds < PROMPT_S
        proc.proc.wait(PROMPT_S)  # exited
    finally:
        proc.kill9()


def test_a_background_correction_of_a_deleted_session_stops_without_an_error(tmp_path, frames, monkeypatch, caplog):
    """The re-fold is held until the session is deleted (its archive closed): it then stops, with no
    error logged and no read of the closed archive's descriptor (whose number another file may
    have taken)."""
    started, gate = threading.Event(), threading.Event()
    counted = corrections.counted

    def held(stream, job):
        started.set()
        gate.wait(120)
        yield from counted(stream, job)

    monkeypatch.setattr(corrections, "counted", held)
    caplog.set_level(logging.INFO, logger="canonical")
    with in_process_server(tmp_path / "data") as url, Client(url) as client:
        session = streamed(client, frames[:4])
        status = session.update_poses({frames[1]["frame_id"]: frames[1]["c2w"]}, wait=False)
        assert status["state"] == "pending"
        assert started.wait(120)
        session.delete()
        with open(tmp_path / "other", "wb") as other:  # may take the archive's descriptor number
            other.write(b"not an archive")
            gate.set()
            refold, = [t for t in threading.enumerate() if t.name == f"correction-{status['correction_id']}"]
            refold.join(120)
    assert not refold.is_alive()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    assert f"background correction {status['correction_id']} stopped: the session was deleted" in caplog.text
