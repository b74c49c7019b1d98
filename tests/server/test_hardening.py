"""No small request can take the service down, on a real server: decompression bombs, per-voxel
widths, view sizes, hostile multipart, huge or slow requests, RGB-only frames, absurd cameras,
depth that gives nothing, the token before the body, and a sweep over every route."""

from __future__ import annotations

import io
import json
import socket
import struct
import time
import zlib

import httpx
import msgpack
import numpy as np
import pytest

from canonical_wire import encode_array

from .harness import TOKEN, VOXEL, ServerProcess, msgpack_frame

AUTH = {"Authorization": f"Bearer {TOKEN}"}
MSGPACK = {**AUTH, "Content-Type": "application/msgpack"}
MAX_BODY = 4 * 1024 * 1024
MAX_RESPONSE = 2 * 1024 * 1024


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
    """A service with small limits and short timeouts, so that each bound is reached cheaply."""
    root = tmp_path_factory.mktemp("hardened")
    proc = ServerProcess(root / "data", root / "server.log", token=TOKEN, max_body_bytes=MAX_BODY,
                         max_image_pixels=640 * 480, max_rgb_only_pixels=320 * 240 - 1, max_label_channels=8,
                         max_response_bytes=MAX_RESPONSE, header_timeout_s=1, read_timeout_s=1, body_timeout_s=3,
                         snapshot_every_seconds=3600)
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def sid(hard, frames):
    r = httpx.post(f"{hard.url}/v1/sessions", json={"voxel_size": VOXEL}, headers=AUTH)
    assert r.status_code == 201, r.text
    session_id = r.json()["id"]
    assert post_frame(hard, session_id, msgpack_frame(frames[0])).status_code == 200
    return session_id


def post_frame(server, session_id, msg=None, **kwargs) -> httpx.Response:
    if msg is not None:
        kwargs = {"content": msgpack.packb(msg, use_bin_type=True), "headers": MSGPACK}
    else:
        kwargs.setdefault("headers", AUTH)
    return httpx.post(f"{server.url}/v1/sessions/{session_id}/frames", timeout=60, **kwargs)


def digest(server, session_id) -> str:
    return httpx.get(f"{server.url}/v1/sessions/{session_id}/digest", headers=AUTH).json()["sha256"]


def assert_error(r: httpx.Response, status: int, field: str) -> dict:
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["field"] == field and error["message"].startswith(f"{field}: "), error
    return error


def raw(port: int, data: bytes, wait: float = 10.0, then: bytes = b"", pause: float = 0.0) -> bytes:
    """Send ``data`` (and ``then`` after ``pause`` s) on a fresh connection; everything read until the
    server closes it or ``wait`` s pass without a byte."""
    with socket.create_connection(("127.0.0.1", port), timeout=wait) as s:
        s.sendall(data)
        if then:
            time.sleep(pause)
            s.sendall(then)
        out = b""
        try:
            while chunk := s.recv(65536):
                out += chunk
        except (socket.timeout, ConnectionResetError):
            pass
        return out


def png_bytes(array: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


def png_header_only(width: int, height: int, bit_depth: int = 8, colour_type: int = 2) -> bytes:
    """A valid PNG signature + IHDR + a tiny IDAT: claims width x height, decodes to almost nothing."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b"")


# -- decompression bombs --------------------------------------------------------------------------
@pytest.mark.parametrize("side", [20000, 2000], ids=["pillow-refuses", "over-the-limit"])
@pytest.mark.parametrize("field, encoding", [("rgb", "msgpack"), ("depth", "msgpack"), ("rgb", "multipart"),
                                             ("depth", "multipart")])
def test_decompression_bomb_is_413_before_decoding(hard, sid, frames, side, field, encoding):
    before = digest(hard, sid)
    bomb = png_header_only(side, side) if field == "rgb" else png_header_only(side, side, 16, 0)
    if encoding == "msgpack":
        changes = {field: bomb} if field == "rgb" else {"depth": bomb, "depth_scale": 1000}
        r = post_frame(hard, sid, {**msgpack_frame(frames[1]), **changes})
    else:
        camera = {"K": frames[1]["K"].tolist(), "c2w": frames[1]["c2w"].tolist(), "depth_scale": 1000}
        rgb = bomb if field == "rgb" else png_bytes(frames[1]["rgb"])
        files = {"rgb": ("c.png", rgb, "image/png"), "camera": (None, json.dumps(camera))}
        if field == "depth":
            files["depth"] = ("d.png", bomb, "image/png")
        r = post_frame(hard, sid, files=files)
    assert_error(r, 413, field)  # an answer read from the connection: it was not reset
    assert digest(hard, sid) == before


# -- per-voxel widths and per-frame channel cost ---------------------------------------------------
def test_label_channels_are_capped(hard, sid, frames):
    before = digest(hard, sid)
    for channels in (1000, 9):
        labels = encode_array(np.zeros((2, 2, channels), np.float32))
        error = assert_error(post_frame(hard, sid, {**msgpack_frame(frames[1]), "labels": labels}), 413, "labels")
        assert f"{channels} label channels exceed the limit of 8" in error["message"]
    # a class map is fused over num_classes channels: its K is capped alike
    class_map = {**msgpack_frame(frames[1]), "labels": encode_array(np.zeros((2, 2), np.uint8)), "num_classes": 9}
    error = assert_error(post_frame(hard, sid, class_map), 413, "num_classes")
    assert "9 label channels exceed the limit of 8" in error["message"]
    assert digest(hard, sid) == before


def test_channel_values_are_capped(hard, frames):
    r = httpx.post(f"{hard.url}/v1/sessions", json={"voxel_size": VOXEL, "features": {"backend": "client"}}, headers=AUTH)
    client_sid = r.json()["id"]
    features = encode_array(np.zeros((2, 2, 512), np.float16))  # 512 x 320 x 240 values at the image's pixels
    assert_error(post_frame(hard, client_sid, {**msgpack_frame(frames[1]), "features": features}), 413, "features")


def test_features_a_session_would_ignore_are_refused(hard, sid, frames):
    before = digest(hard, sid)
    features = encode_array(np.zeros((4, 4, 3), np.float32))
    error = assert_error(post_frame(hard, sid, {**msgpack_frame(frames[1]), "features": features}), 422, "features")
    assert "features.backend" in error["message"]
    assert digest(hard, sid) == before


# -- view sizes -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def labelled(hard, frames):
    r = httpx.post(f"{hard.url}/v1/sessions", json={"voxel_size": VOXEL}, headers=AUTH)
    session_id = r.json()["id"]
    labels = encode_array(np.random.default_rng(0).random((6, 8, 4)).astype(np.float32))  # the image's shape
    assert post_frame(hard, session_id, {**msgpack_frame(frames[0]), "labels": labels}).status_code == 200
    return session_id


def _view(frame, width: int, height: int) -> dict:
    f = 0.9 * width
    return {"K": [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], "c2w": frame["c2w"].tolist(),
            "width": width, "height": height}


def _view_request(server, session_id, route, method, view, **params):
    url = f"{server.url}/v1/sessions/{session_id}/{route}"
    headers = {**AUTH, "Accept": "application/msgpack"}
    if method == "POST":
        return httpx.post(url, json=view, params=params, headers=headers, timeout=60)
    K = view["K"]
    query = {"pose": ",".join(str(x) for row in view["c2w"] for x in row), "K": f"{K[0][0]},{K[1][1]},{K[0][2]},{K[1][2]}",
             "width": view["width"], "height": view["height"], **params}
    return httpx.get(url, params=query, headers=headers, timeout=60)


@pytest.mark.parametrize("method", ["GET", "POST"])
@pytest.mark.parametrize("route", ["render", "features", "segmentation"])
def test_view_responses_are_bounded_by_pixels_times_channels(hard, labelled, frames, route, method):
    # 400x300: render 5, features 17, labels 5 float channels -> 2.4 to 8.2 MB of maps, above 2 MiB
    error = assert_error(_view_request(hard, labelled, route, method, _view(frames[0], 400, 300)), 413, "width")
    assert "max_response_bytes" in error["message"]
    small = _view_request(hard, labelled, route, method, _view(frames[0], 160, 120))
    assert small.status_code == 200, small.text
    assert len(small.content) <= MAX_RESPONSE


# -- multipart ------------------------------------------------------------------------------------
def _multipart(frame, camera: dict | None = None, extra: list | None = None) -> dict:
    camera = camera or {"K": frame["K"].tolist(), "c2w": frame["c2w"].tolist()}
    return {"files": [("rgb", ("c.png", png_bytes(frame["rgb"]), "image/png")), ("camera", (None, json.dumps(camera))),
                      *(extra or [])]}


def test_hostile_multipart_headers_are_refused(hard, sid):
    boundary = "xyz"
    disposition = "form-data; name=rgb" + "; a=1" * 40_000  # about 280 KB of parameters
    body = f"--{boundary}\r\nContent-Disposition: {disposition}\r\n\r\nx\r\n--{boundary}--\r\n".encode()
    r = post_frame(hard, sid, content=body, headers={**AUTH, "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert_error(r, 400, "body")
    many = "".join(f"--{boundary}\r\nContent-Disposition: form-data; name=p{i}\r\n\r\nx\r\n" for i in range(50))
    r = post_frame(hard, sid, content=(many + f"--{boundary}--\r\n").encode(),
                   headers={**AUTH, "Content-Type": f"multipart/form-data; boundary={boundary}"})
    assert_error(r, 400, "body")


@pytest.mark.parametrize("name", ["rgb", "camera", "image"])
def test_repeated_parts_are_refused(hard, sid, frames, name):
    before = digest(hard, sid)
    kwargs = _multipart(frames[1])
    kwargs["files"].append((name, kwargs["files"][0 if name != "camera" else 1][1]))
    assert_error(post_frame(hard, sid, **kwargs), 422, "rgb" if name == "image" else name)
    assert digest(hard, sid) == before


@pytest.mark.parametrize("field, value", [("K", "strings"), ("c2w", True), ("depth_scale", "1000"), ("width", True),
                                          ("height", 240.0), ("frame_id", 3)])
def test_camera_json_is_strictly_typed(hard, sid, frames, field, value):
    frame = frames[1]
    camera = {"K": frame["K"].tolist(), "c2w": frame["c2w"].tolist(), "depth_scale": 1000}
    if field == "K":
        camera["K"] = [[str(x) for x in row] for row in camera["K"]]
    else:
        camera[field] = value
    depth = png_bytes(np.round(frame["depth"].astype(np.float64) * 1000).astype(np.uint16))
    before = digest(hard, sid)
    assert_error(post_frame(hard, sid, **_multipart(frame, camera, [("depth", ("d.png", depth, "image/png"))])), 422, field)
    assert digest(hard, sid) == before


@pytest.mark.parametrize("field, value", [("width", "160"), ("height", True), ("max_gaussians", "10"), ("K", [[True, 0, 1]] * 3),
                                          ("background", ["0", "0", "0"])])
def test_view_bodies_are_strictly_typed(hard, sid, frames, field, value):
    body = {**_view(frames[0], 160, 120), field: value}
    r = httpx.post(f"{hard.url}/v1/sessions/{sid}/render", json=body, headers=AUTH)
    assert r.status_code == 422 and r.json()["error"]["field"].split(".")[0] == field, r.text


UNPARSABLE_JSON = [("nested too deeply", b"[" * 100_000), ("nested objects", b'{"a":' * 100_000),
                   ("not UTF-8", b'{"voxel_size": "\xff"}'), ("cut short", b'{"voxel_size": ')]


@pytest.mark.parametrize("body", [c[1] for c in UNPARSABLE_JSON], ids=[c[0] for c in UNPARSABLE_JSON])
def test_a_json_body_that_cannot_be_parsed_is_malformed_on_every_json_route(hard, sid, body):
    operations, _ = _operations(hard)
    routes = [(method, path) for method, path, op in operations
              if "application/json" in op.get("requestBody", {}).get("content", {})]
    assert len(routes) >= 5
    before = digest(hard, sid)
    for method, path in routes:
        r = httpx.request(method, hard.url + path.replace("{session_id}", sid), content=body,
                          headers={**AUTH, "Content-Type": "application/json"}, timeout=30)
        assert_error(r, 400, "body")
        assert r.json()["error"]["code"] == "malformed_body", (method, path, r.text)
    assert digest(hard, sid) == before


def test_a_camera_part_nested_too_deeply_is_refused_naming_it(hard, sid, frames):
    kwargs = _multipart(frames[1])
    kwargs["files"][1] = ("camera", (None, "[" * 100_000))
    assert_error(post_frame(hard, sid, **kwargs), 422, "camera")


# -- huge and slow requests -----------------------------------------------------------------------
def _head(path: str, length: int | None, token: str = TOKEN, content_type: str = "application/msgpack") -> bytes:
    lines = [f"POST {path} HTTP/1.1", "Host: test", f"Authorization: Bearer {token}", f"Content-Type: {content_type}"]
    if length is not None:
        lines.append(f"Content-Length: {length}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def _status_and_error(reply: bytes) -> tuple[int, dict]:
    head, _, body = reply.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(body)["error"]


def test_huge_content_length_without_a_body_is_answered_at_once(hard, sid):
    reply = raw(hard.port, _head(f"/v1/sessions/{sid}/frames", 10**12), wait=5)
    status, error = _status_and_error(reply)
    assert status == 413 and error["field"] == "body"


def test_slow_request_head_is_closed(hard):
    assert raw(hard.port, b"POST /v1/sessions HTTP/1.1\r\nHost: te", wait=10) == b""  # closed, nothing answered
    assert raw(hard.port, b"", wait=10) == b""  # a connection that never sends


def test_stalled_body_is_408(hard, sid):
    reply = raw(hard.port, _head(f"/v1/sessions/{sid}/frames", 1000) + b"\x81" * 10, wait=10)
    status, error = _status_and_error(reply)
    assert status == 408 and error["field"] == "body" and "no data" in error["message"]


def test_trickled_body_is_408(hard, sid):
    with socket.create_connection(("127.0.0.1", hard.port), timeout=10) as s:
        s.sendall(_head(f"/v1/sessions/{sid}/frames", 1000))
        reply = b""
        for _ in range(40):  # a byte every 0.25 s: never stalls for read_timeout_s, never completes
            try:
                s.sendall(b"\x81")
            except OSError:
                break
            time.sleep(0.25)
            s.setblocking(False)
            try:
                reply += s.recv(65536)
            except BlockingIOError:
                pass
            s.setblocking(True)
            if reply:
                break
    status, error = _status_and_error(reply)
    assert status == 408 and "not complete within" in error["message"]


# -- RGB-only frames, absurd cameras, depth that gives nothing --------------------------------------
def test_large_rgb_only_frame_is_413(hard, sid, frames):
    before = digest(hard, sid)
    msg = msgpack_frame(frames[1])
    msg.pop("depth")
    error = assert_error(post_frame(hard, sid, msg), 413, "rgb")
    assert "without depth" in error["message"]
    assert digest(hard, sid) == before


def _K(frame, **entries):
    K = np.array(frame["K"], np.float64)
    for (i, j), name in (((0, 0), "fx"), ((1, 1), "fy"), ((0, 2), "cx"), ((1, 2), "cy")):
        if name in entries:
            K[i, j] = entries[name]
    return K.tolist()


def _moved(frame, t):
    c2w = np.array(frame["c2w"], np.float64)
    c2w[:3, 3] = t
    return c2w.tolist()


ABSURD = [
    ("fx 1e30", lambda f: {"K": _K(f, fx=1e30)}, "K"),
    ("fy 1e-6", lambda f: {"K": _K(f, fy=1e-6)}, "K"),
    ("cx far outside", lambda f: {"K": _K(f, cx=1e7)}, "K"),
    ("translation 1e12", lambda f: {"c2w": _moved(f, [1e12, 0, 0])}, "c2w"),
    ("image 1x1", lambda f: {"rgb": encode_array(np.zeros((1, 1, 3), np.uint8)), "depth": None, "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
     "rgb"),
]


@pytest.mark.parametrize("make, field", [c[1:] for c in ABSURD], ids=[c[0] for c in ABSURD])
def test_absurd_cameras_are_422(hard, sid, frames, make, field):
    before = digest(hard, sid)
    msg = {**msgpack_frame(frames[1]), **make(frames[1])}
    msg = {k: v for k, v in msg.items() if v is not None}
    assert_error(post_frame(hard, sid, msg), 422, field)
    if field in ("K", "c2w"):  # the same camera asked for as a view
        view = {**_view(frames[0], 320, 240), field: make(frames[0])[field]}
        assert_error(httpx.post(f"{hard.url}/v1/sessions/{sid}/render", json=view, headers=AUTH), 422, field)
    assert digest(hard, sid) == before


@pytest.mark.parametrize("depth, message", [(0.0, "no valid pixel"), (np.nan, "no valid pixel"), (2000.0, "no pixel lies within")],
                         ids=["zero", "nan", "millimetres-as-metres"])
def test_depth_that_gives_nothing_is_reported(hard, frames, depth, message):
    r = httpx.post(f"{hard.url}/v1/sessions", json={"voxel_size": VOXEL}, headers=AUTH)
    session_id = r.json()["id"]
    msg = {**msgpack_frame(frames[1]), "depth": encode_array(np.full((240, 320), depth, np.float32))}
    r = post_frame(hard, session_id, msg)
    assert r.status_code == 200, r.text
    report = r.json()
    assert report["observations"] == 0 and len(report["warnings"]) == 1 and message in report["warnings"][0]
    good = post_frame(hard, session_id, msgpack_frame(frames[2])).json()
    assert good["observations"] > 0 and good["warnings"] == []


# -- the token before the body --------------------------------------------------------------------
@pytest.mark.parametrize("path", ["/docs", "/redoc", "/openapi.json", "/metrics", "/v1/sessions", "/docs/oauth2-redirect"])
def test_with_a_token_everything_but_healthz_is_closed(hard, path):
    assert_error(httpx.get(f"{hard.url}{path}"), 401, "Authorization")
    assert_error(httpx.get(f"{hard.url}{path}", headers={"Authorization": "Bearer wrong"}), 401, "Authorization")
    assert httpx.get(f"{hard.url}/healthz").status_code == 200


def test_healthz_tells_the_session_count_only_to_the_token(hard, sid):
    assert httpx.get(f"{hard.url}/healthz").json() == {"status": "ok"}
    assert httpx.get(f"{hard.url}/healthz", headers={"Authorization": "Bearer wrong"}).json() == {"status": "ok"}
    held = len(httpx.get(f"{hard.url}/v1/sessions", headers=AUTH).json()["sessions"])
    assert httpx.get(f"{hard.url}/healthz", headers=AUTH).json() == {"status": "ok", "sessions": held}


def test_wrong_token_is_refused_before_the_body_is_read(hard, sid):
    length = 64 * 1024 * 1024
    # only 1 MiB of the announced 64 MiB is ever sent: an answer proves the body was not awaited
    reply = raw(hard.port, _head(f"/v1/sessions/{sid}/frames", length, token="wrong") + b"\x00" * (1 << 20), wait=10)
    status, error = _status_and_error(reply)
    assert status == 401 and error["field"] == "Authorization"


# -- a sweep over every route the service declares -------------------------------------------------
def _operations(server) -> list[tuple[str, str, dict]]:
    spec = httpx.get(f"{server.url}/openapi.json", headers=AUTH).json()
    return [(method.upper(), path, op) for path, item in spec["paths"].items() for method, op in item.items()], spec


def _wrong_value(schema: dict):
    kinds = {schema.get("type")} | {s.get("type") for s in schema.get("anyOf", [])}
    if kinds & {"number", "integer", "array", "boolean"}:
        return "not-a-number"
    return {"nested": ["object"]}


def test_every_route_answers_bad_input_with_a_4xx_naming_a_field(hard, sid):
    operations, spec = _operations(hard)
    assert len(operations) >= 10
    schemas = spec["components"]["schemas"]
    cases = []
    for method, path, op in operations:
        url = hard.url + path.replace("{session_id}", sid)
        cases.append(("oversize", method, url, {"content": b"\x00" * (MAX_BODY + 1), "headers": AUTH}))
        if "{session_id}" in path:
            cases.append(("unknown session", method, hard.url + path.replace("{session_id}", "no-such-session"), {"headers": AUTH}))
        body = op.get("requestBody", {}).get("content", {})
        if body:
            cases.append(("malformed", method, url, {"content": b"\xff{\x00", "headers": {**AUTH, "Content-Type": "application/json"}}))
        ref = body.get("application/json", {}).get("schema", {}).get("$ref")
        if ref:
            for name, prop in schemas[ref.split("/")[-1]]["properties"].items():
                cases.append((f"wrong-typed {name}", method, url, {"json": {name: _wrong_value(prop)}, "headers": AUTH}))
        for param in op.get("parameters", []):
            if param["in"] == "query":
                cases.append((f"wrong-typed {param['name']}", method, url, {"params": {param["name"]: "[[nope"}, "headers": AUTH}))
    assert len(cases) >= 60
    failures = []
    for label, method, url, kwargs in cases:
        if method == "DELETE" and label != "unknown session" and label != "oversize":
            continue  # a valid DELETE has no body or query to get wrong
        r = httpx.request(method, url, timeout=30, **kwargs)
        error = r.json().get("error", {}) if r.headers.get("content-type", "").startswith("application/json") else {}
        if not (400 <= r.status_code < 500 and error.get("field")):
            failures.append(f"{label} {method} {url}: {r.status_code} {r.text[:200]}")
    assert not failures, "\n".join(failures)
    assert httpx.get(f"{hard.url}/v1/sessions/{sid}", headers=AUTH).status_code == 200  # still there
    metrics = httpx.get(f"{hard.url}/metrics", headers=AUTH).text
    assert 'status="500"' not in metrics
