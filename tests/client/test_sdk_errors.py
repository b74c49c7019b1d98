"""The SDK's own errors and edges against a real service: no answer is `ServiceUnreachable`, odd
arguments are refused naming them before anything is sent, numpy values travel as numbers, a quiet
session's event stream outlives the request timeout, and downloads to one path at once stay whole."""

from __future__ import annotations

import os
import socket
import threading
import time

import httpx
import numpy as np
import pytest

from client.sdk import CanonicalError, Client, ServiceUnreachable
from client.sdk.session import Session

VOXEL = 0.008


def umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # free once closed: nothing listens there


def test_no_answer_is_service_unreachable_naming_the_request():
    with Client(f"http://127.0.0.1:{closed_port()}", max_retries=1, max_wait=0.01) as client:
        with pytest.raises(ServiceUnreachable, match=r"GET http://127\.0\.0\.1:\d+/healthz: ConnectError") as info:
            client.health()  # said in the SDK's terms
        assert isinstance(info.value, ConnectionError) and isinstance(info.value.__cause__, httpx.ConnectError)
        with pytest.raises(ServiceUnreachable, match="POST .*/v1/sessions: ConnectError"):
            client.create_session(voxel_size=VOXEL)  # not retried: a POST that may have made a session


def test_a_client_that_never_reached_the_service_is_not_kept_waiting():
    """Nothing listens at the URL (a typo, a service not started): the default retries, which ride
    through a restart of a service the client was using, would only make the user wait half a minute."""
    with Client(f"http://127.0.0.1:{closed_port()}") as client:
        attempts = []
        send = client._http.send
        client._http.send = lambda *a, **k: attempts.append(1) or send(*a, **k)
        with pytest.raises(ServiceUnreachable, match="ConnectError"):
            client.sessions()
        assert len(attempts) == 1


@pytest.mark.parametrize("url", ["127.0.0.1:8000", "ftp://127.0.0.1:8000", "", "http://[::1"])
def test_a_url_the_client_cannot_use_is_refused_naming_it(url):
    with pytest.raises(ValueError, match="^url: expected the service's http:// or https:// address"):
        Client(url)


@pytest.mark.parametrize("kwargs, field", [
    ({"max_retries": -1}, "max_retries"), ({"max_retries": 1.5}, "max_retries"), ({"max_retries": True}, "max_retries"),
    ({"timeout": 0}, "timeout"), ({"timeout": float("nan")}, "timeout"), ({"max_wait": -1}, "max_wait"),
])
def test_client_arguments_are_checked_naming_them(kwargs, field):
    with pytest.raises(ValueError, match=f"^{field}: "):
        Client("http://127.0.0.1:1", **kwargs)
    Client("http://127.0.0.1:1", timeout=None, max_retries=0, max_wait=0).close()  # the edges that are fine


@pytest.mark.parametrize("body", [b'{"error": null}', b'{"error": "x"}', b"[1, 2]", b"<html>bad gateway</html>"])
def test_an_error_answer_in_another_shape_is_still_a_canonical_error(body):
    error = Client._error(httpx.Response(502, content=body))
    assert isinstance(error, CanonicalError) and error.status == 502 and error.code == "error"


def test_view_arguments_are_refused_naming_them_before_anything_is_sent(server):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        K, pose = np.array([[300.0, 0, 80], [0, 300, 60], [0, 0, 1]]), np.eye(4)
        bad_pose = pose.copy()
        bad_pose[0, 3] = np.nan
        for args, kwargs, field in [((K, bad_pose, 160, 120), {}, "c2w"), ((K, pose, "abc", 120), {}, "width"),
                                    ((K, pose, 160, 12.5), {}, "height"), ((K, pose, 160, 120), {"background": 0.5}, "background"),
                                    ((K, pose, 160, 120), {"max_gaussians": 1.5}, "max_gaussians")]:
            with pytest.raises(ValueError, match=f"^{field}: "):
                session.render(*args, **kwargs)
        view = session.render(K, pose, np.int64(160), 120.0)  # numpy integers and whole floats are whole numbers
        assert view["rgb"].shape == (120, 160, 3)
        assert np.array_equal(session.render(K, pose[:3], 160, 120)["rgb"], view["rgb"])  # a 3x4 pose, as the service takes


def test_numpy_numbers_in_session_settings_travel_as_numbers(server):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=np.float32(0.01), max_voxels=np.int64(10**6),
                                        range={"near": np.float64(0.2)})
        config = session.stats()["config"]
        assert config["max_voxels"] == 10**6 and config["range"]["near"] == 0.2
        assert abs(config["voxel_size"] - 0.01) < 1e-6
        with pytest.raises(ValueError, match=r"^range\.near: expected a finite number"):
            client.create_session(range={"near": np.float32("nan")})


def test_a_quiet_sessions_events_outlive_the_request_timeout(server, frames):
    """The service writes a keep-alive comment every 15 s; a client timeout of 1 s used to end the
    stream with a ReadTimeout after a second of quiet."""
    with Client(server.url, timeout=1.0) as client:
        session = client.create_session(voxel_size=VOXEL)
        events, got, failed = session.events(), [], []

        def read():
            try:
                got.extend(name for name, _ in (next(events), next(events)))
            except Exception as exc:  # what a reader would see
                failed.append(exc)

        reader = threading.Thread(target=read)
        reader.start()
        time.sleep(2.5)
        session.add_frame(**frames[0])
        reader.join(30)
        events.close()
        assert not failed and got == ["state", "fold"]


def test_downloads_to_one_path_at_once_each_leave_a_whole_file(server, frames, tmp_path):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        session.add_frame(**frames[0])
        target, errors = tmp_path / "scene.ply", []

        def export():
            try:
                session.export_ply(target)
            except Exception as exc:
                errors.append(exc)

        threads = [threading.Thread(target=export) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        answer = httpx.get(f"{server.url}/v1/sessions/{session.id}/gaussians.ply")
        expected = answer.content  # sent a block of rows at a time, its length said up front
        assert int(answer.headers["content-length"]) == len(expected) and "transfer-encoding" not in answer.headers
        assert not errors and target.read_bytes() == expected
        assert target.stat().st_mode & 0o777 == 0o666 & ~umask()  # as any file the user makes
        assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]  # no temporary file left


def test_a_download_cut_short_is_service_unreachable_and_leaves_no_file(tmp_path):
    """Exports are written as they arrive: a connection that ends before the answer's Content-Length
    is asked again from the start (as a GET that got no answer is), and after the last retry it is
    `ServiceUnreachable` naming the request, neither the file nor its temporary file left."""
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    whole = b"ply\n" + b"x" * 100_000

    def serve(answers: int, cut: int):  # the first ``cut`` answers end early, the rest are whole
        for k in range(answers):
            conn, _ = listener.accept()
            with conn:
                conn.recv(65536)
                conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\nContent-Length: %d\r\n"
                             b"Connection: close\r\n\r\n" % len(whole) + (whole[:5000] if k < cut else whole))

    server = threading.Thread(target=serve, args=(2, 2), daemon=True)
    server.start()
    with Client(f"http://127.0.0.1:{port}", max_retries=1, max_wait=0.01) as client:
        with pytest.raises(ServiceUnreachable, match=r"GET http://127\.0\.0\.1:\d+/v1/sessions/s/gaussians\.ply: RemoteProtocolError"):
            Session(client, "s").export_ply(tmp_path / "scene.ply")
    server.join(10)
    assert list(tmp_path.iterdir()) == []
    server = threading.Thread(target=serve, args=(2, 1), daemon=True)  # cut once: the retry writes it whole
    server.start()
    with Client(f"http://127.0.0.1:{port}", max_retries=1, max_wait=0.01) as client:
        assert Session(client, "s").export_ply(tmp_path / "scene.ply").read_bytes() == whole
    server.join(10)
    listener.close()
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]


def test_a_refused_export_makes_no_folder(server, tmp_path):
    with Client(server.url) as client:
        with pytest.raises(CanonicalError) as err:
            Session(client, "no-such-session").export_ply(tmp_path / "new" / "scene.ply")
    assert err.value.status == 404 and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["webp", "16-bit grey png"])
def test_colour_bytes_the_service_refuses_are_refused_whatever_the_depths_size(server, frames, kind):
    """The SDK fits colour to lower-resolution depth (and big frames without depth to the service's
    limit) by decoding it: bytes the service would not take are sent as they are instead, so that the
    frame is refused naming rgb as it is with depth at the colour's size (not folded in wrong colours)."""
    import io

    from PIL import Image

    rgb = frames[0]["rgb"]
    buf = io.BytesIO()
    if kind == "webp":
        Image.fromarray(rgb).save(buf, format="WEBP", lossless=True)
    else:
        Image.fromarray((rgb[..., 0].astype(np.uint16) * 257)).save(buf, format="PNG")
    depth = frames[0]["depth"]
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        for d in (depth, depth[::2, ::2]):  # at the colour's size, and at half of it
            with pytest.raises(CanonicalError) as err:
                session.add_frame(rgb=buf.getvalue(), K=frames[0]["K"], c2w=frames[0]["c2w"], depth=d)
            assert err.value.status == 422 and err.value.field == "rgb", err.value
        assert session.stats()["frames"] == 0
