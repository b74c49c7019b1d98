"""The viewer's HTTP side against a real service: pages, the image route, input cameras, fold events,
the CLI's ``view``, and a shutdown with an event stream open."""

from __future__ import annotations

import io
import json
import signal
import subprocess
import sys
import time

import httpx
import numpy as np
import pytest
from PIL import Image

from client.sdk import png_to_array

from ..server.harness import REPO, TOKEN, VOXEL, ServerProcess, colours_solved
from .walls import FAR, NEAR, wall_frames

AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture(scope="module")
def walls(client):
    """A session of two frames of two walls (near left, far right) with labels 0 and 2."""
    session = client.create_session(voxel_size=0.02)
    frames = wall_frames()
    for kwargs in frames:
        session.add_frame(**kwargs)
    assert colours_solved(session)  # the pictures compared below then show one solution
    return session, frames


def image_query(kwargs: dict, width: int = 128, height: int = 96, **extra) -> dict:
    K, c2w = kwargs["K"], kwargs["c2w"]
    return {"pose": ",".join(map(str, np.asarray(c2w).ravel())), "K": f"{K[0][0]},{K[1][1]},{K[0][2]},{K[1][2]}",
            "width": width, "height": height, **extra}


def get_image(server, session_id, params, headers=AUTH) -> httpx.Response:
    return httpx.get(f"{server.url}/v1/sessions/{session_id}/image", params=params, headers=headers, timeout=60)


def test_pages_are_open_and_data_needs_the_token(server, walls):
    session, frames = walls
    for path in ("/", f"/sessions/{session.id}/view", "/viewer/view.js", "/viewer/style.css"):
        r = httpx.get(server.url + path)
        assert r.status_code == 200, path
        assert session.id not in r.text  # a page carries no session data
    assert httpx.get(server.url + "/viewer/view.js").headers["content-type"].startswith("text/javascript")
    for path in ("/viewer/missing.js", "/viewer/..%2Fapp.py", "/viewer/.hidden"):
        r = httpx.get(server.url + path)
        assert r.status_code == 404 and r.json()["error"]["field"] == "path", path
    for path in ("/v1/viewer/info", "/v1/viewer/sessions", f"/v1/sessions/{session.id}/cameras",
                 f"/v1/sessions/{session.id}/events"):
        r = httpx.get(server.url + path)
        assert r.status_code == 401 and r.json()["error"]["field"] == "Authorization", path
    assert get_image(server, session.id, image_query(frames[-1]), headers={}).status_code == 401


def test_the_viewers_list_and_colours_answer_in_their_documented_schemas(server, walls):
    session, frames = walls
    rows = httpx.get(f"{server.url}/v1/viewer/sessions", headers=AUTH).json()["sessions"]
    row, = [r for r in rows if r["id"] == session.id]
    stats = session.stats()
    assert {k: row[k] for k in ("frames", "voxels", "gaussians", "label_dim")} == {
        k: stats[k] for k in ("frames", "voxels", "gaussians", "label_dim")}
    assert row["frames"] == len(frames) and time.time() - 3600 < row["last_fold"] <= time.time()
    info = httpx.get(f"{server.url}/v1/viewer/info", headers=AUTH).json()
    for colours in (info["depth_colormap"], info["label_palette"]):
        assert len(colours) > 2 and all(len(c) == 3 and all(0 <= v <= 255 for v in c) for c in colours)
    paths = httpx.get(f"{server.url}/openapi.json", headers=AUTH).json()["paths"]
    for path, model in (("/v1/viewer/sessions", "ViewerSessionList"), ("/v1/viewer/info", "ViewerInfo")):
        assert paths[path]["get"]["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith(model)


def test_png_image_is_the_render_routes_png_and_jpeg_webp_decode_close_to_it(server, walls):
    session, frames = walls
    reference = png_to_array(session.render_png(frames[-1]["K"], frames[-1]["c2w"], 128, 96))
    r = get_image(server, session.id, image_query(frames[-1]))
    assert r.headers["content-type"] == "image/png"
    np.testing.assert_array_equal(png_to_array(r.content), reference)
    timing = dict(part.strip().split(";dur=") for part in r.headers["server-timing"].split(","))
    assert set(timing) == {"render", "picture", "encode"} and all(float(v) >= 0 for v in timing.values())
    for fmt, magic in (("jpeg", b"\xff\xd8\xff"), ("webp", b"RIFF")):
        r = get_image(server, session.id, image_query(frames[-1], format=fmt, quality=90))
        assert r.headers["content-type"] == f"image/{fmt}" and r.content.startswith(magic)
        decoded = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB")).astype(float)
        assert np.abs(decoded - reference).mean() < 6.0


def test_depth_alpha_and_labels_pictures_say_how_to_read_them(server, walls):
    from server.viewer import DEPTH_LUT, PALETTE

    session, frames = walls
    r = get_image(server, session.id, image_query(frames[-1], mode="depth"))
    near, far = map(float, r.headers["x-canonical-depth-range"].split(","))
    assert 0.9 < near < 1.1 and 1.9 < far < 2.1
    depth = png_to_array(r.content)
    index = lambda c: int(np.argmin(np.abs(DEPTH_LUT.astype(int) - c).sum(1)))  # noqa: E731
    assert index(depth[48, 20]) < 10 and index(depth[48, 108]) > 245  # the walls at the ends of the scale
    for bad in ("1e-300,2e-300", "-1e300,0", "-1e308,1e308", "nan,1", "1,1", "0,1e400"):
        r = get_image(server, session.id, image_query(frames[-1], mode="depth", depth_range=bad))
        assert r.status_code == 422 and r.json()["error"]["field"] == "depth_range", (bad, r.text)
    fixed = get_image(server, session.id, image_query(frames[-1], mode="depth", depth_range="0,4"))
    assert fixed.headers["x-canonical-depth-range"] == "0,4"
    assert abs(index(png_to_array(fixed.content)[48, 20]) - 64) <= 3  # 1 m of 0..4 m
    r = get_image(server, session.id, image_query(frames[-1], mode="alpha"))
    assert 0.5 < float(r.headers["x-canonical-coverage"]) <= 1.0
    assert NEAR - 0.1 < float(r.headers["x-canonical-centre-depth"]) < FAR + 0.1  # both walls are in the middle
    r = get_image(server, session.id, image_query(frames[-1], mode="labels"))
    assert r.headers["x-canonical-labels"] == "0,2"
    labels = png_to_array(r.content)
    np.testing.assert_array_equal(labels[48, 20], PALETTE[1])
    np.testing.assert_array_equal(labels[48, 108], PALETTE[3])


@pytest.mark.parametrize("params, status, field", [
    ({"mode": "normals"}, 422, "mode"),
    ({"format": "gif"}, 422, "format"),
    ({"quality": 0}, 422, "quality"),
    ({"mode": "depth", "depth_range": "2,1"}, 422, "depth_range"),
    ({"mode": "depth", "depth_range": "1"}, 422, "depth_range"),
    ({"width": 10_000, "height": 10_000}, 413, "width"),
])
def test_bad_image_requests_name_the_field(server, walls, params, status, field):
    session, frames = walls
    r = get_image(server, session.id, {**image_query(frames[-1]), **params})
    assert r.status_code == status and r.json()["error"]["field"] == field


def test_a_viewer_id_over_64_characters_is_refused_naming_its_header(server, walls):
    session, frames = walls
    r = get_image(server, session.id, image_query(frames[-1]), headers={**AUTH, "X-Canonical-Viewer": "v" * 65})
    assert r.status_code == 422 and r.json()["error"]["field"] == "x-canonical-viewer"
    r = get_image(server, session.id, image_query(frames[-1]), headers={**AUTH, "X-Canonical-Viewer": "v" * 64})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"


def test_labels_of_a_session_without_labels_is_409(server, client):
    session = client.create_session(voxel_size=VOXEL)
    kwargs = {k: v for k, v in wall_frames()[0].items() if k != "labels"}
    session.add_frame(**kwargs)
    r = get_image(server, session.id, image_query(kwargs, mode="labels"))
    assert r.status_code == 409 and r.json()["error"]["code"] == "no_labels"
    r = httpx.get(f"{server.url}/v1/sessions/nope/image", params=image_query(kwargs), headers=AUTH)
    assert r.status_code == 404


def read_events(lines, count: int) -> list[tuple[str, dict]]:
    events, name = [], None
    for line in lines:
        if line.startswith("event:"):
            name = line[6:].strip()
        elif line.startswith("data:"):
            events.append((name, json.loads(line[5:])))
            if len(events) == count:
                return events
    raise AssertionError(f"stream ended after {events}")


def test_event_stream_sends_state_then_one_fold_per_frame_with_its_camera(server, client):
    session = client.create_session(voxel_size=0.02)
    frames = wall_frames()
    with httpx.stream("GET", f"{server.url}/v1/sessions/{session.id}/events", headers=AUTH, timeout=60) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        lines = r.iter_lines()
        assert read_events(lines, 1) == [("state", {"frames": 0, "voxels": 0, "label_dim": 0})]
        for k, kwargs in enumerate(frames):
            report = session.add_frame(**kwargs)
            (name, event), = read_events(lines, 1)
            assert name == "fold" and event["frames"] == k + 1 and event["report"] == report
            assert event["voxels"] == session.stats()["voxels"]
            np.testing.assert_allclose(np.reshape(event["camera"]["c2w"], (4, 4)), kwargs["c2w"])
            assert event["camera"]["K"] == [100.0, 100.0, 64.0, 48.0] and event["camera"]["frame_index"] == k
    # a replayed frame (same frame_id) is not a new fold: the camera track holds each frame once
    track = httpx.get(f"{server.url}/v1/sessions/{session.id}/cameras", headers=AUTH).json()
    assert [c["frame_index"] for c in track["cameras"]] == [0, 1] and track["frames"] == 2


def test_an_event_stream_with_every_stands_one_event_for_the_folds_of_an_interval(server, client):
    session = client.create_session(voxel_size=0.02)
    walls = wall_frames()[0]
    steps = 6
    with httpx.stream("GET", f"{server.url}/v1/sessions/{session.id}/events", params={"every": 2.0},
                      headers=AUTH, timeout=60) as r:
        lines = r.iter_lines()
        assert read_events(lines, 1)[0][0] == "state"
        reports = [session.add_frame(**walls)]
        (name, first), = read_events(lines, 1)  # the first fold after a quiet interval comes at once
        assert name == "fold" and first["folds"] == 1 and first["report"] == reports[0]
        assert first["previous_time"] is None and first["warned"] is None
        assert [c["frame_index"] for c in first["cameras"]] == [0] and first["camera"] == first["cameras"][0]
        for k in range(1, steps):  # five more well inside the interval: one event stands for them
            c2w = np.array(walls["c2w"], dtype=float)
            c2w[0, 3] = 0.005 * k
            reports.append(session.add_frame(**{**walls, "c2w": c2w}))
        received = [first]
        while received[-1]["frames"] < steps:
            received.append(read_events(lines, 1)[0][1])
    assert len(received) < steps
    assert sum(e["folds"] for e in received) == steps
    assert [c["frame_index"] for e in received for c in e["cameras"]] == list(range(steps))
    last = received[-1]
    assert last["report"] == reports[-1] and last["camera"] == last["cameras"][-1]
    assert last["voxels"] == session.stats()["voxels"] and last["warned"] is None
    assert received[-2]["time"] <= last["previous_time"] < last["time"]


@pytest.mark.parametrize("every", ["0", "-1", "61", "soon"])
def test_an_event_stream_with_a_bad_every_is_refused_naming_it(server, walls, every):
    session, _ = walls
    r = httpx.get(f"{server.url}/v1/sessions/{session.id}/events", params={"every": every}, headers=AUTH, timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == "every"


def test_cameras_outlive_a_restart_and_an_open_stream_does_not_hold_up_shutdown(tmp_path):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_frames=1, warm_up=False)
    proc.start()
    try:
        from client.sdk import Client

        with Client(proc.url) as c:
            session = c.create_session(voxel_size=0.02)
            for kwargs in wall_frames():
                session.add_frame(**kwargs, frame_id=f"f{kwargs['c2w'][0, 3]}")
            session.add_frame(**wall_frames()[0], frame_id="f0.01")  # a replay: no new camera
        before = httpx.get(f"{proc.url}/v1/sessions/{session.id}/cameras").json()["cameras"]
        assert len(before) == 2
        with httpx.stream("GET", f"{proc.url}/v1/sessions/{session.id}/events", timeout=60) as r:
            lines = r.iter_lines()  # held: a dropped iterator would close the connection from this side
            read_events(lines, 1)
            t0 = time.monotonic()
            proc.proc.terminate()
            proc.proc.wait(20)  # the stream ends with the service: no kill needed
            assert time.monotonic() - t0 < 15
        assert proc.proc.returncode in (0, -signal.SIGTERM)  # uvicorn re-raises SIGTERM after its graceful shutdown
        proc.start()
        after = httpx.get(f"{proc.url}/v1/sessions/{session.id}/cameras").json()
        assert after["cameras"] == before and after["last_fold"] is not None and after["last_fold_age"] >= 0
    finally:
        proc.stop()


def test_cli_view_prints_the_page_url_and_never_the_token(server, walls):
    session, _ = walls
    env = {"PATH": "/usr/bin:/bin", "CANONICAL_API_TOKEN": TOKEN}
    out = subprocess.run([sys.executable, "-m", "client.cli", "view", "--url", server.url, "--session", session.id],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == f"{server.url}/sessions/{session.id}/view"
    assert TOKEN not in out.stdout
    bad = subprocess.run([sys.executable, "-m", "client.cli", "view", "--url", server.url, "--session", "nope"],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and "nope" not in bad.stdout
