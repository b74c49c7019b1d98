"""Frames in flight against a real service: `Session.add_frames` and `canonical stream` keep several
posted, the service folds them in their ``Frame-Index`` order whatever order they arrive in, and a
refused frame stops the stream with what was acknowledged."""

from __future__ import annotations

import io
import re
import shutil
import socket
import threading
import time

import httpx
import numpy as np
import pytest
from PIL import Image

from canonical_core.datasets import load_tsdf_fusion
from client.cli import main
from client.cli.capture import capture_frames
from client.sdk import MSGPACK, Client, ServiceUnreachable, StreamRefused, StreamStopped, frame_body, unpack
from tests.conftest import folded_scene
from tests.server.harness import VOXEL, ServerProcess, small_frames, wait_for

pytestmark = pytest.mark.realdata

WAIT_S = 3.0  # the service's frame_order_wait_s here: a gap that stays open is refused this soon


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    proc = ServerProcess(root / "data", root / "server.log", frame_order_wait_s=WAIT_S, snapshot_every_seconds=3600)
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def frames(shelf_dir) -> list[dict]:
    return small_frames(shelf_dir, count=8, step=5)


@pytest.fixture(scope="module")
def digests(service, frames) -> dict[int, str]:
    """The digests of the frames posted one at a time, without a Frame-Index: after k frames."""
    with Client(service.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        out = {}
        for kwargs in frames:
            session.add_frame(**kwargs)
            out[session.stats()["frames"]] = session.digest()["sha256"]
        return out


def post(client: httpx.Client, session_id: str, kwargs: dict, index) -> httpx.Response:
    return client.post(f"/v1/sessions/{session_id}/frames", content=frame_body(**kwargs),
                       headers={"Content-Type": MSGPACK, "Frame-Index": str(index)})


def test_frames_in_flight_fold_in_order_and_give_the_one_by_one_scene(service, frames, digests):
    with Client(service.url) as client:
        for in_flight in (2, 4):
            session = client.create_session(voxel_size=VOXEL)
            reports = list(session.add_frames(frames, in_flight=in_flight))
            assert [r["frame_index"] for r in reports] == list(range(len(frames)))
            assert all(r["new_voxels"] >= 0 and "ms" in r for r in reports)  # each answer is its fold report
            assert session.digest()["sha256"] == digests[len(frames)]


def test_frames_arriving_in_reverse_fold_in_their_numbers_order(service, frames, digests):
    """The last frame is posted first, the first one last: each waits for the frames before it."""
    frames = frames[:4]
    with Client(service.url) as sdk, httpx.Client(base_url=service.url, timeout=60) as http:
        session = sdk.create_session(voxel_size=VOXEL)
        answers: dict[int, httpx.Response] = {}

        def send(k: int) -> None:
            answers[k] = post(http, session.id, frames[k], k)

        threads = []
        for k in reversed(range(len(frames))):
            threads.append(threading.Thread(target=send, args=(k,)))
            threads[-1].start()
            time.sleep(0.05)  # so that they arrive in this (reversed) order
        for t in threads:
            t.join()
        assert {k: r.status_code for k, r in answers.items()} == {k: 200 for k in range(len(frames))}
        assert all(answers[k].json()["frame_index"] == k for k in answers)
        assert session.digest()["sha256"] == digests[4]


def test_a_refused_frame_stops_the_stream_and_says_what_was_acknowledged(service, frames, digests):
    bad = {**frames[3], "depth": frames[3]["depth"][:-8]}  # not the colour image's size: the service refuses it
    with Client(service.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        got = []
        with pytest.raises(StreamRefused) as info:
            for report in session.add_frames(frames[:3] + [bad] + frames[4:], in_flight=4):
                got.append(report["frame_index"])
        refused = info.value
        assert got == [0, 1, 2] and refused.index == 3 and refused.acknowledged == 3
        assert refused.status == 422 and refused.field == "depth" and "frame 3 refused (the session holds the 3 frames before it)" in str(refused)
        assert session.stats()["frames"] == 3  # the frames posted behind it were not folded
        # the stream goes on from the refused frame, corrected
        assert [r["frame_index"] for r in session.add_frames(frames[3:])] == list(range(3, len(frames)))
        assert session.digest()["sha256"] == digests[len(frames)]


def test_a_frame_the_client_cannot_send_stops_the_stream_at_once_and_posts_nothing_after_it(service, frames, digests):
    """A 4x4 K on the third frame (the SDK's own check refuses it while the frames around it are built on
    other workers): the stream stops with `StreamStopped` naming the frame and what was acknowledged,
    at once, and no frame after it was posted (the service would have held those, numbered for a place
    no frame fills, for frame_order_wait_s)."""
    bad = {**frames[2], "K": np.eye(4)}
    with Client(service.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        got, start = [], time.perf_counter()
        with pytest.raises(StreamStopped) as info:
            for report in session.add_frames(frames[:2] + [bad] + frames[3:8], in_flight=4):
                got.append(report["frame_index"])
        assert time.perf_counter() - start < WAIT_S / 2
        # no frame after it is waiting on the service (their bodies would be held until WAIT_S)
        held = lambda: int(re.search(r"^canonical_request_body_bytes (\d+)",  # noqa: E731
                                     httpx.get(f"{service.url}/metrics").text, re.M).group(1))
        assert wait_for(lambda: held() == 0, WAIT_S / 3)
        stopped = info.value
        assert not isinstance(stopped, StreamRefused) and isinstance(stopped.__cause__, ValueError)
        assert got == [0, 1] and stopped.index == 2 and stopped.acknowledged == 2 and "K:" in str(stopped)
        # nothing was posted after it: the corrected stream goes on from it at once
        assert [r["frame_index"] for r in session.add_frames(frames[2:], in_flight=3)] == list(range(2, len(frames)))
        assert session.digest()["sha256"] == digests[len(frames)]


def test_a_frame_id_repeated_within_a_stream_is_a_replay_that_takes_no_place(service, frames, digests):
    """f0, f1, f2, f1 again, f3, ...: the repeat is answered with f1's report and the frames after it
    keep their places (before, they were numbered one place too far and waited frame_order_wait_s for
    a frame that never came)."""
    named = [{**f, "frame_id": f"f{k}"} for k, f in enumerate(frames[:5])]
    with Client(service.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        start = time.perf_counter()
        reports = list(session.add_frames(named[:3] + [named[1]] + named[3:], in_flight=3))
        assert time.perf_counter() - start < WAIT_S
        assert [r["frame_index"] for r in reports] == [0, 1, 2, 1, 3, 4] and reports[3] == reports[1]
        assert session.digest()["sha256"] == digests[5]
        # a frame the session held before the stream, met mid-stream: stopped at once, saying what to do
        with pytest.raises(StreamStopped, match="frame_id 'f1': the session holds it already .* first_index=6"):
            list(session.add_frames([{**frames[5], "frame_id": "f5"}, named[1], {**frames[6], "frame_id": "f6"}],
                                    in_flight=3, first_index=5))
        assert time.perf_counter() - start < 2 * WAIT_S


def test_frame_index_out_of_place_is_refused_naming_it(service, frames):
    with Client(service.url) as sdk, httpx.Client(base_url=service.url, timeout=60) as http:
        session = sdk.create_session(voxel_size=VOXEL)
        assert post(http, session.id, frames[0], 0).status_code == 200
        late = post(http, session.id, frames[1], 0)  # its place is taken
        assert late.status_code == 409
        assert late.json()["error"] == {"code": "frame_out_of_order", "field": "Frame-Index", "message":
                                         "Frame-Index: frame 0 comes too late: the session holds 1 frames, so the next "
                                         "one is frame 1"}
        gap = post(http, session.id, frames[2], 2)  # frame 1 never comes
        assert gap.status_code == 409
        assert gap.json()["error"]["message"].startswith(f"Frame-Index: frame 2 waited {WAIT_S:g} s for frame 1")
        for value in ("-1", "one", "1_0", "+1", "1.0", "0x1"):  # int() reads "1_0" as 10, "+1" as 1
            bad = http.post(f"/v1/sessions/{session.id}/frames", content=frame_body(**frames[1]),
                            headers={"Content-Type": MSGPACK, "Frame-Index": value})
            assert bad.status_code == 422 and bad.json()["error"]["field"] == "Frame-Index"
        assert session.stats()["frames"] == 1  # nothing of these changed the session


def test_a_numbered_frame_refused_before_it_is_read_stops_the_frames_behind_it_at_once(service, frames):
    """A body of the wrong type (415) or over the size limit (413, by its Content-Length, answered
    before the route runs) refuses its frame as a malformed one does: the frame numbered after it
    is told at once, not after frame_order_wait_s."""
    with Client(service.url) as sdk, httpx.Client(base_url=service.url, timeout=60) as http:
        for refuse in ("type", "size"):
            session = sdk.create_session(voxel_size=VOXEL)
            assert post(http, session.id, frames[0], 0).status_code == 200
            if refuse == "type":
                r = http.post(f"/v1/sessions/{session.id}/frames", content=frame_body(**frames[1]),
                              headers={"Content-Type": "application/json", "Frame-Index": "1"})
                assert r.status_code == 415, r.text
            else:
                with socket.create_connection(("127.0.0.1", service.port)) as raw:
                    raw.sendall(f"POST /v1/sessions/{session.id}/frames HTTP/1.1\r\nHost: x\r\nContent-Type: {MSGPACK}"
                                f"\r\nContent-Length: {10**12}\r\nFrame-Index: 1\r\n\r\n".encode())
                    assert raw.recv(64).startswith(b"HTTP/1.1 413")
            start = time.perf_counter()
            behind = post(http, session.id, frames[2], 2)
            assert behind.status_code == 409 and time.perf_counter() - start < WAIT_S / 2, behind.text
            assert "follows frame 1, which was refused" in behind.json()["error"]["message"]
            assert post(http, session.id, frames[1], 1).status_code == 200  # resent, the stream goes on
            assert session.stats()["frames"] == 2


def test_a_retried_frame_with_its_frame_id_is_a_replay_in_a_pipeline(service, frames):
    with Client(service.url) as sdk, httpx.Client(base_url=service.url, timeout=60) as http:
        session = sdk.create_session(voxel_size=VOXEL)
        named = [{**f, "frame_id": f"f{k}"} for k, f in enumerate(frames[:3])]
        first = list(session.add_frames(named, in_flight=3))
        again = post(http, session.id, named[1], 1)  # an answer lost, the frame sent again
        assert again.status_code == 200 and again.headers["Idempotent-Replay"] == "true"
        assert again.json() == first[1] and session.stats()["frames"] == 3
        other = post(http, session.id, {**named[0], "frame_id": "f1"}, 1)
        assert other.status_code == 409 and other.json()["error"]["field"] == "frame_id"


def streamed_digest(service, folder, frames: int, capsys) -> dict:
    """`canonical stream FOLDER` of every 10th frame, ``frames`` of them, into ``service``, with the CLI's
    defaults: the digest of the session it made."""
    assert main(["stream", str(folder), "--voxel-size", str(VOXEL), "--stride", "10", "--max-frames", str(frames),
                 "--url", service.url]) == 0
    session_id = capsys.readouterr().out.strip().splitlines()[-1]
    with Client(service.url) as client:
        return client.session(session_id).digest()


def test_stream_sends_the_captures_own_files_and_folds_what_the_loader_reads(service, shelf_dir, capsys):
    capture = load_tsdf_fusion(shelf_dir, stride=10, max_frames=4)
    sent = list(capture_frames(capture))
    files = capture.source(0)
    assert sent[0]["rgb"] == files.color.read_bytes() and sent[0]["depth"] == files.depth.read_bytes()
    assert sent[0]["depth_scale"] == 1000.0 and sent[0]["frame_id"] == "frame-000015"
    digest = streamed_digest(service, shelf_dir, 4, capsys)
    assert digest["frames"] == 4 and digest["sha256"] == folded_scene(capture, VOXEL).digest()


def test_a_frame_of_another_size_than_the_captures_is_refused_naming_its_file(shelf_dir, tmp_path):
    capture = tmp_path / "capture"
    shutil.copytree(shelf_dir, capture)
    odd = sorted(capture.rglob("*.color.png"))[10]
    Image.open(odd).resize((1280, 960)).save(odd)  # the capture's intrinsics are for 640x480
    with pytest.raises(ValueError, match=rf"{odd.name}: image is 1280x960, the capture's are 640x480"):
        list(capture_frames(load_tsdf_fusion(capture, stride=10, max_frames=2)))


def test_stream_of_a_capture_with_depth_at_half_the_colours_size_sends_the_colour_fitted(service, shelf_dir, tmp_path,
                                                                                          capsys):
    """A phone's capture: depth PNGs at a fraction of the colour's pixels. The stream sends the depth's
    file as it is and the colour's file brought to the depth's pixels (not the whole image), and the
    service folds the frames the loader reads."""
    capture = tmp_path / "capture"
    shutil.copytree(shelf_dir, capture)
    for path in sorted(capture.rglob("*.depth.png"))[:20]:
        depth = np.asarray(Image.open(path))
        Image.fromarray(np.ascontiguousarray(depth[::2, ::2])).save(path)
    loaded = load_tsdf_fusion(capture, stride=10, max_frames=2)
    sent = list(capture_frames(loaded))
    files = loaded.source(0)
    assert sent[0]["depth"] == files.depth.read_bytes() and sent[0]["rgb"] == files.color.read_bytes()
    body = unpack(frame_body(**sent[0]))
    assert np.asarray(Image.open(io.BytesIO(body["rgb"]))).shape == (240, 320, 3)
    assert len(body["rgb"]) < len(files.color.read_bytes()) / 2
    digest = streamed_digest(service, capture, 2, capsys)
    assert digest["frames"] == 2 and digest["sha256"] == folded_scene(loaded, VOXEL).digest()


@pytest.mark.parametrize("damage, error", [
    ("depth.png", "error: 422 invalid_value: frame 2 refused (the session holds the 2 frames before it): depth: "
                  "expected a 16-bit"),  # the service's refusal, its files named after it
    ("color.png", "frame-000002.color.png: unreadable image"),  # the client's, reading the capture
], ids=["refused by the service", "unreadable here"])
def test_stream_stops_at_a_refused_frame_and_says_how_to_go_on(service, shelf_dir, tmp_path, capsys, damage, error):
    capture = tmp_path / "capture"
    capture.mkdir()
    (capture / "intrinsics.K.txt").write_bytes((shelf_dir / "intrinsics.K.txt").read_bytes())
    original = load_tsdf_fusion(shelf_dir, stride=10, max_frames=4)
    for k in range(len(original)):
        source = original.source(k)
        for kind, path in (("color.png", source.color), ("depth.png", source.depth), ("pose.txt", None)):
            target = capture / f"frame-{k:06d}.{kind}"
            if path is not None:
                target.write_bytes(path.read_bytes())
            else:
                target.write_text("\n".join(" ".join(f"{x:.9g}" for x in row) for row in source.c2w))
    if damage == "depth.png":  # an 8-bit depth image: sent as it is, refused by the service
        Image.fromarray(np.zeros((480, 640), np.uint8)).save(capture / "frame-000002.depth.png")
    else:  # not an image at all
        (capture / "frame-000002.color.png").write_bytes((shelf_dir / "intrinsics.K.txt").read_bytes())
    code = main(["stream", str(capture), "--voxel-size", str(VOXEL), "--url", service.url])
    err = capsys.readouterr().err
    assert code == 1
    assert error in err
    if damage == "depth.png":
        assert f"(files: {capture / 'frame-000002.color.png'}, {capture / 'frame-000002.depth.png'})" in err
    assert "stopped: 2 frames in" in err
    session_id = err.split("continue with --session ")[1].split()[0]
    with Client(service.url) as client:
        assert client.session(session_id).stats()["frames"] == 2


def test_a_service_gone_after_the_last_frame_still_gets_the_stream_told_and_how_to_go_on(shelf_dir, tmp_path, capsys,
                                                                                          monkeypatch):
    """The service dies once every frame is acknowledged, before the summary is read: the stream says
    what was acknowledged and how to go on, at once, instead of a bare connection error after a
    second half minute of retries."""
    from client.sdk import Session

    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_seconds=3600).start()
    stats = Session.stats
    monkeypatch.setattr(Session, "stats", lambda self: proc.kill9() or stats(self))
    try:
        code = main(["stream", str(shelf_dir), "--max-frames", "3", "--stride", "10", "--scale", "0.25",
                     "--voxel-size", str(VOXEL), "--url", proc.url])
    finally:
        proc.kill9()
    err = capsys.readouterr().err
    assert code == 1 and "all 3 frames acknowledged; the service could not be reached" in err, err
    assert re.search(r"continue with --session \w+", err), err


def test_frames_with_ids_ride_through_a_kill9_and_restart_of_the_service_and_frames_without_are_not_resent(
        tmp_path, frames, digests):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_seconds=3600).start()
    try:
        client = Client(proc.url, max_retries=10)
        session = client.create_session(voxel_size=VOXEL)
        stream = [{**kwargs, "frame_id": f"frame-{k}"} for k, kwargs in enumerate(frames)]
        for kwargs in stream[:3]:
            session.add_frame(**kwargs)
        proc.kill9()
        # the rest is sent while the service is down: each frame is retried until it is back
        restart = threading.Timer(1.0, proc.start, kwargs={"same_port": True})
        restart.start()
        try:
            reports = list(session.add_frames(stream[3:], first_index=3))
        finally:
            restart.join()
        assert [r["frame_index"] for r in reports] == list(range(3, len(frames)))
        assert session.digest()["sha256"] == digests[len(frames)]  # every frame folded once

        proc.kill9()
        with pytest.raises(ServiceUnreachable):  # without an id a resent frame might fold twice: not resent
            session.add_frame(**{**frames[0], "frame_id": None})
    finally:
        proc.kill9()
