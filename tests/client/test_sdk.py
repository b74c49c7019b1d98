"""The SDK against a real service: numpy in, numpy out, errors as CanonicalError, 429 retries."""

from __future__ import annotations

import io
import itertools
import threading

import httpx
import numpy as np
import pytest
import torch
from PIL import Image

from canonical_core import load_ply, load_splat
from canonical_core.datasets.images import depth_from_uint16, read_depth, read_rgb
from client.cli import build_parser
from client.sdk import (CanonicalError, Client, DownscaledFrame, Session, decode_array, encode_array, exact_sensor_depth,
                        frame_body, scaled_intrinsics, unpack)
from tests.server.harness import SOLVE_WAIT_S, colours_solved

VOXEL = 0.008


def test_array_codec_roundtrip():
    for a in (np.arange(12, dtype=np.uint8).reshape(2, 2, 3), np.linspace(0, 1, 6, dtype=np.float16).reshape(3, 2),
              np.array([[1, 65535]], np.uint16), np.random.default_rng(0).random((4, 5, 2)).astype(np.float32)):
        b = decode_array(encode_array(a))
        assert b.dtype == a.dtype and np.array_equal(a, b)
    assert decode_array(encode_array(np.ones(3))).dtype == np.float32  # float64 travels as float32
    with pytest.raises(ValueError, match="int64"):
        encode_array(np.ones(3, np.int64))


def test_without_a_url_the_sdk_and_the_cli_find_the_service_at_canonical_url(server, monkeypatch):
    monkeypatch.setenv("CANONICAL_URL", server.url)
    with Client() as c:
        assert c.health()["status"] == "ok"
    assert build_parser().parse_args(["sessions"]).url == server.url
    monkeypatch.delenv("CANONICAL_URL")  # neither set nor given: where `canonical serve` listens by default
    assert build_parser().parse_args(["sessions"]).url == "http://127.0.0.1:8000"


def test_session_events_read_the_folds_as_they_come_batched_or_not_and_end_on_delete(server, frames):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        each, batched = session.events(), session.events(every=30.0)
        assert next(each) == next(batched) == ("state", {"frames": 0, "voxels": 0, "label_dim": 0})
        reports = [session.add_frame(**kwargs) for kwargs in frames[:3]]
        folds = [next(each) for _ in reports]
        assert [name for name, _ in folds] == ["fold"] * 3 and [e["report"] for _, e in folds] == reports
        # every 30 s: the first fold at once, the next two within the interval not yet
        name, first = next(batched)
        assert name == "fold" and first["folds"] == 1 and first["report"] == reports[0]
        session.delete()
        assert next(each) == ("deleted", {"id": session.id})  # the stream's last event
        assert list(each) == []
        batched.close()  # a reader may leave at any time: the service frees the stream's slot
        with pytest.raises(CanonicalError) as err:
            next(client.create_session(voxel_size=VOXEL).events(every=0))
        assert (err.value.status, err.value.field) == (422, "every")


@pytest.mark.realdata
def test_session_roundtrip(server, frames, tmp_path):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL, features={"dim": 8})
        for i, kwargs in enumerate(frames[:2]):
            report = session.add_frame(**kwargs)
            assert report["frame_index"] == i and report["new_voxels"] > 0
        assert client.session(session.id).id == session.id
        assert session.id in [s["id"] for s in client.sessions()]
        health = client.health()
        assert health["status"] == "ok" and health["sessions"] >= 1

        kwargs = frames[0]
        h, w = kwargs["rgb"].shape[:2]
        assert colours_solved(session)  # the render and the PNG below then show the same colours
        view = session.render(kwargs["K"], kwargs["c2w"], w, h)
        assert view["rgb"].dtype == np.uint8 and view["rgb"].shape == (h, w, 3)
        assert view["depth"].dtype == np.float32 and view["alpha"].dtype == np.float32
        png = Image.open(io.BytesIO(session.render_png(kwargs["K"], kwargs["c2w"], w, h)))
        assert np.array_equal(np.asarray(png), view["rgb"])
        feats = session.features(kwargs["K"], kwargs["c2w"], w // 2, h // 2)
        assert feats["features"].dtype == np.float16 and feats["features"].shape == (h // 2, w // 2, 8)

        stats = session.stats()
        assert stats["frames"] == 2 and stats["config"]["features"]["dim"] == 8
        ply = load_ply(session.export_ply(tmp_path / "s.ply"))
        splat = load_splat(session.export_splat(tmp_path / "s.splat"))
        assert len(ply) == len(splat) == stats["gaussians"]
        assert len(load_ply(session.export_ply(tmp_path / "lod.ply", max_gaussians=100))) == 100

        with pytest.raises(CanonicalError) as err:
            session.add_frame(kwargs["rgb"], kwargs["K"], np.full((4, 4), np.nan), depth=kwargs["depth"])
        assert (err.value.status, err.value.code, err.value.field) == (422, "invalid_value", "c2w")
        assert session.stats()["frames"] == 2

        session.delete()
        with pytest.raises(CanonicalError) as err:
            client.session(session.id)
        assert err.value.status == 404 and err.value.field == "session_id"


def test_waiting_for_colours_ends_once_solved_at_once_with_none_due_and_when_frames_keep_coming(server, frames):
    with Client(server.url) as client:
        waits = []
        empty = client.create_session(voxel_size=VOXEL)
        assert empty.wait_for_colours(progress=waits.append)["frames"] == 0 and waits == []  # nothing to solve
        off = client.create_session(voxel_size=VOXEL, colour_solve={"views": 0})
        off.add_frame(**frames[0])
        assert off.wait_for_colours(progress=waits.append)["colours_solved_frames"] is None and waits == []  # solve off

        session = client.create_session(voxel_size=VOXEL)
        for kwargs in frames:
            session.add_frame(**kwargs)
        stats = session.wait_for_colours(SOLVE_WAIT_S)  # nobody renders: the pause alone gets them solved
        assert stats["colours_solved_frames"] == stats["frames"] == len(frames)
        assert session.wait_for_colours(progress=waits.append) == session.stats() and waits == []  # solved: no wait

        streaming, stop = threading.Event(), threading.Event()

        def stream():  # frames back to back, with no pause for a solve to begin in
            for i in itertools.count():
                if stop.is_set():
                    return
                session.add_frame(**{**frames[i % len(frames)], "frame_id": f"live-{i}"})  # an id sent again is that frame again
                streaming.set()
        sender = threading.Thread(target=stream)
        sender.start()
        try:
            assert streaming.wait(60)
            stats = session.wait_for_colours(SOLVE_WAIT_S, progress=waits.append)
        finally:
            stop.set()
            sender.join()
        # a live stream is not waited for: it returned at its first look after a frame came
        assert len(waits) == 1 and stats["frames"] > waits[0]["frames"] > len(frames)
        assert stats["colours_solved_frames"] == len(frames)
        session.delete(), off.delete(), empty.delete()


@pytest.mark.realdata
def test_sensor_depth_units_fold_as_the_same_metres(server, frames):
    """Depth sent as 16-bit sensor units (what a depth camera gives) folds exactly as the float32
    metres the service converts them to; `exact_sensor_depth` finds such units only where lossless."""
    metres = frames[0]["depth"]
    units, scale = exact_sensor_depth(metres)
    assert units.dtype == np.uint16 and scale == 1000.0 and (units > 0).any()
    assert np.array_equal(depth_from_uint16(units, scale).view(np.uint32), metres.view(np.uint32))  # the service's conversion
    assert exact_sensor_depth(np.where(metres > 0, metres + np.float32(1e-5), 0)) is None  # not whole units
    assert exact_sensor_depth(np.where(metres > 0, np.nan, metres)) is None
    assert exact_sensor_depth(np.full((2, 2), 70.0, np.float32)) is None  # past 16 bits at every scale
    with Client(server.url) as client:
        digests = []
        for as_units in (False, True):
            session = client.create_session(voxel_size=VOXEL)
            for kwargs in frames[:2]:
                if as_units:
                    kwargs = {**kwargs, **dict(zip(("depth", "depth_scale"), exact_sensor_depth(kwargs["depth"])))}
                session.add_frame(**kwargs)
            digests.append({k: v for k, v in session.digest().items() if k != "id"})
            session.delete()
    assert digests[0] == digests[1]


@pytest.mark.parametrize("depth, depth_scale, field", [
    (np.ones((4, 4), np.uint16), None, "depth_scale"),  # units without what they measure
    (np.ones((4, 4), np.uint16), 0, "depth_scale"),
    (np.ones((4, 4), np.int32), float("nan"), "depth_scale"),
    (np.full((4, 4), 70000, np.int32), 1000, "depth"),  # past 16 bits
    (np.full((4, 4), -1, np.int16), 1000, "depth"),
    (np.ones((4, 4), np.float32), 1000, "depth_scale"),  # metres already
])
def test_sensor_depth_errors_name_the_field_before_anything_is_sent(depth, depth_scale, field):
    session = Session(Client("http://127.0.0.1:9"), "unused")  # nothing listens: a request would fail otherwise
    rgb, K, c2w = np.zeros((4, 4, 3), np.uint8), np.eye(3), np.eye(4)
    with pytest.raises(ValueError, match=rf"^{field}:"):
        session.add_frame(rgb, K, c2w, depth=depth, depth_scale=depth_scale)


@pytest.mark.parametrize("channels", [4, 2, 1])
def test_colour_that_is_not_rgb_is_refused_by_the_service_whatever_the_codec(channels):
    """[H, W, 4] or grey [H, W, 1] arrays: the compact codec does not make a PNG of them (which the
    service would take, its alpha dropped or its grey copied), so both codecs get the same 422."""
    from server.wire import frame_from_message

    rgb = np.zeros((12, 16, channels), np.uint8)
    K = np.array([[20.0, 0, 8], [0, 20, 6], [0, 0, 1]])
    for codec in ("compact", "raw"):
        with pytest.raises(ValueError, match=r"rgb: expected shape \[H, W, 3\]"):
            frame_from_message(unpack(frame_body(rgb, K, np.eye(4), codec=codec)))


def test_compact_frames_are_lossless_and_small(shelf_dir):
    """Every form of `frame_body`'s compact codec decodes, on the service's side, to the frame the
    raw arrays give: colour as PNG, depth as zstandard uint16 (integer, or float that 16-bit units
    hold exactly) or float32, a capture's own PNG and JPEG bytes untouched."""
    from server.wire import frame_from_message

    color, depth_png = shelf_dir / "frames" / "frame-000015.color.png", shelf_dir / "frames" / "frame-000015.depth.png"
    rgb, metres = read_rgb(color), read_depth(depth_png, 1000.0)
    K, c2w = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]]), np.eye(4)
    noisy = metres + np.float32(1e-4) * (metres > 0)  # not a multiple of any sensor unit

    def decoded(**kwargs):
        body = frame_body(rgb=kwargs.pop("rgb", rgb), K=K, c2w=c2w, **kwargs)
        return unpack(body), frame_from_message(unpack(body)), len(body)

    raw_msg, raw, raw_bytes = decoded(depth=metres, codec="raw")
    assert raw_msg["rgb"]["dtype"] == "uint8" and raw_msg["depth"]["dtype"] == "float32" and "codec" not in raw_msg["depth"]
    cases = {"float metres": {"depth": metres}, "millimetres": {"depth": np.rint(metres * 1000).astype(np.uint16), "depth_scale": 1000},
             "the capture's files": {"rgb": color.read_bytes(), "depth": depth_png.read_bytes(), "depth_scale": 1000}}
    for name, kwargs in cases.items():
        msg, frame, size = decoded(**kwargs)
        assert msg["rgb"][:8] == b"\x89PNG\r\n\x1a\n", name
        assert torch.equal(frame.rgb, raw.rgb) and torch.equal(frame.depth, raw.depth), name
        assert size < raw_bytes / 3, name
    assert decoded(**cases["millimetres"])[0]["depth"]["codec"] == "zstd"
    assert decoded(**cases["the capture's files"])[0]["rgb"] == color.read_bytes()
    msg, frame, _ = decoded(depth=noisy)
    assert msg["depth"]["dtype"] == "float32" and msg["depth"]["codec"] == "zstd" and np.array_equal(frame.depth.numpy(), noisy)
    jpeg = io.BytesIO()
    Image.fromarray(rgb).save(jpeg, format="JPEG", quality=90)
    msg, frame, _ = decoded(rgb=jpeg.getvalue(), depth=metres)
    assert msg["rgb"] == jpeg.getvalue() and np.array_equal(frame.rgb.numpy(), np.asarray(Image.open(jpeg).convert("RGB")))
    # label scores travel zstandard-compressed and decode to the raw ones bit for bit; a class map
    # travels as int16 ids with its K, whatever integer type it came in
    thirds = (np.arange(rgb.shape[1]) * 3 // rgb.shape[1])[None, :].repeat(rgb.shape[0], 0)
    scores = np.eye(3, dtype=np.float32)[thirds]
    raw_msg, raw, raw_bytes = decoded(depth=metres, labels=scores, codec="raw")
    msg, frame, size = decoded(depth=metres, labels=scores)
    assert msg["labels"]["codec"] == "zstd" and "codec" not in raw_msg["labels"]
    assert torch.equal(frame.labels, raw.labels) and size < raw_bytes / 8
    ids = np.where(thirds == 1, -5, thirds)  # int64, a negative id: no class
    for given in (ids, ids.astype(np.int32), thirds.astype(np.uint8)):
        msg, frame, map_size = decoded(depth=metres, labels=given, num_classes=4)
        assert msg["labels"]["dtype"] == "int16" and msg["labels"]["codec"] == "zstd" and msg["num_classes"] == 4
        assert frame.num_classes == 4 and frame.labels.tolist() == np.maximum(given.astype(np.int64), -1).tolist() and map_size < size
    with pytest.raises(ValueError, match="^num_classes: required with a class map"):
        frame_body(rgb, K, c2w, labels=thirds)
    with pytest.raises(ValueError, match="^num_classes: goes with a class map"):
        frame_body(rgb, K, c2w, labels=scores, num_classes=3)
    with pytest.raises(ValueError, match="^codec: expected one of"):
        frame_body(rgb, K, c2w, codec="png")


@pytest.mark.realdata
def test_burst_gets_429_and_the_sdk_retries_through(server, frames):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        session.add_frame(**frames[0])
    kwargs = frames[0]
    h, w = kwargs["rgb"].shape[:2]
    body = {"K": kwargs["K"].tolist(), "c2w": kwargs["c2w"].tolist(), "width": w, "height": h}
    url = f"{server.url}/v1/sessions/{session.id}/render"

    # raw burst: with a one-job queue some requests are refused with 429 + Retry-After
    n = 8
    barrier, results = threading.Barrier(n), []

    def raw():
        with httpx.Client(timeout=60) as http:
            barrier.wait()
            r = http.post(url, json=body)
            results.append((r.status_code, r.headers.get("retry-after"), r.json()["error"]["code"] if r.status_code != 200 else None))

    threads = [threading.Thread(target=raw) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    statuses = sorted(s for s, _, _ in results)
    assert set(statuses) <= {200, 429} and 200 in statuses and 429 in statuses, statuses
    assert all(retry == "1" and code == "busy" for s, retry, code in results if s == 429)

    # the SDK honours Retry-After and gets every request through
    barrier, ok, errors = threading.Barrier(n), [], []

    def sdk():
        try:
            with Client(server.url, max_retries=20) as c:
                s = Session(c, session.id)  # no request yet: the burst starts at the barrier
                barrier.wait()
                ok.append(s.render(kwargs["K"], kwargs["c2w"], w, h)["rgb"].shape)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=sdk) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and ok == [(h, w, 3)] * n
    with Client(server.url) as client:
        assert 'canonical_http_responses_total{status="429"}' in client.metrics()
        client.session(session.id).delete()


def test_scaled_intrinsics_keep_pixel_centres_on_integers():
    """The SDK's K for a resized image agrees with the library's `Camera.scaled` (pixel u spans
    u - 0.5 .. u + 0.5, so the image's edges stay its edges) and scales each axis by its own factor."""
    from canonical_core import Camera

    K = np.array([[600.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(scaled_intrinsics(K, 0.5, 0.5), Camera(K, np.eye(4), 640, 480).scaled(0.5).K64())
    sx, sy = 858 / 1080, 1526 / 1920
    small = scaled_intrinsics(K, sx, sy)
    for u, v in ((-0.5, -0.5), (1079.5, 1919.5), (300.0, 700.0)):  # the corners' edges and a pixel centre
        ray = np.linalg.solve(K, [u, v, 1.0])
        projected = small @ ray
        np.testing.assert_allclose(projected[:2] / projected[2], [(u + 0.5) * sx - 0.5, (v + 0.5) * sy - 0.5])


@pytest.mark.realdata
def test_colour_over_lower_resolution_depth_travels_at_the_depths_size(frames):
    """A phone's 1920x1440 colour with its 256x192 LiDAR depth: the SDK sends the colour area-averaged
    to the depth's pixels, with K resized to match, exactly what the service makes of the whole image
    (the rule of `canonical_core.resample`), in a small fraction of the bytes, whether it is given as
    an array or as image bytes. The raw codec, and depth of another shape, send the image as it is."""
    from canonical_core import Camera
    from canonical_core.resample import area_resize
    from client.sdk import encode_png

    kwargs = frames[0]
    h, w = kwargs["rgb"].shape[:2]
    big = np.asarray(Image.fromarray(kwargs["rgb"]).resize((1920, 1440), Image.BILINEAR))
    K = scaled_intrinsics(kwargs["K"], 1920 / w, 1440 / h)
    depth = np.asarray(Image.fromarray(kwargs["depth"]).resize((256, 192), Image.NEAREST))
    sent = unpack(frame_body(big, K, kwargs["c2w"], depth=depth))
    rgb = np.asarray(Image.open(io.BytesIO(sent["rgb"])))
    assert np.array_equal(rgb, area_resize(big, (256, 192)))
    assert np.array_equal(np.array(sent["K"]), Camera(K, kwargs["c2w"], 1920, 1440).resized(256, 192).K64())
    assert len(frame_body(big, K, kwargs["c2w"], depth=depth)) < len(encode_png(big)) / 10  # the whole image's PNG
    png = unpack(frame_body(encode_png(big), K, kwargs["c2w"], depth=depth))  # image bytes: decoded and fitted too
    assert png["rgb"] == sent["rgb"] and png["K"] == sent["K"]
    assert np.shape(decode_array(unpack(frame_body(big, K, kwargs["c2w"], depth=depth, codec="raw"))["rgb"])) == big.shape
    for other in (depth[:, :200], np.zeros((1440, 1920), np.float32)):  # another camera's depth; the image's size
        assert np.asarray(Image.open(io.BytesIO(unpack(frame_body(big, K, kwargs["c2w"], depth=other))["rgb"]))).shape == big.shape
    png = Image.fromarray((depth * 1000).astype(np.uint16))  # depth as a sensor's 16-bit PNG bytes: its header's size
    buf = io.BytesIO()
    png.save(buf, format="PNG")
    sent = unpack(frame_body(big, K, kwargs["c2w"], depth=buf.getvalue(), depth_scale=1000))
    assert np.asarray(Image.open(io.BytesIO(sent["rgb"]))).shape == (192, 256, 3)


@pytest.mark.realdata
def test_frames_without_depth_over_the_limit_are_downscaled_to_it(server, frames):
    """A phone's 1920x1080 frame without depth is over the service's 1.3 MP limit for such frames: the
    SDK sends it downscaled to the limit the service publishes, with K scaled to match, and says so
    once; ``downscale=False`` sends it as it is and gets the service's 413."""
    from PIL import Image as PILImage

    kwargs = frames[0]
    h, w = kwargs["rgb"].shape[:2]
    big = np.asarray(PILImage.fromarray(kwargs["rgb"]).resize((1920, 1080), PILImage.BILINEAR))
    K = scaled_intrinsics(kwargs["K"], 1920 / w, 1080 / h)
    with Client(server.url) as client:
        limit = client.limits()["max_rgb_only_pixels"]
        assert limit == 1280 * 1024  # the service's setting
        session = client.create_session(voxel_size=VOXEL)
        with pytest.raises(CanonicalError) as refused:
            session.add_frame(big, K, kwargs["c2w"], downscale=False)
        assert (refused.value.status, refused.value.field) == (413, "rgb")
        with pytest.warns(DownscaledFrame, match=r"1920x1080 .* downscaled to 1526x858") as caught:
            session.add_frame(big, K, kwargs["c2w"], frame_id="a")
            session.add_frame(big, K, kwargs["c2w"], frame_id="b")
        assert len({str(w.message) for w in caught}) == 1
        camera = httpx.get(f"{server.url}/v1/sessions/{session.id}/cameras").json()["cameras"][0]
        assert (camera["width"], camera["height"]) == (1526, 858) and 1526 * 858 <= limit
        fx, fy, cx, cy = camera["K"]
        np.testing.assert_allclose([fx, fy, cx, cy], scaled_intrinsics(K, 1526 / 1920, 858 / 1080)[[0, 1, 0, 1], [0, 1, 2, 2]])
        session.delete()


@pytest.mark.realdata
def test_integer_class_maps_fold_as_one_hot_scores(server, frames):
    """A segmentation network's [H, W] class map is the common form of labels: the SDK sends it as
    ids with K (the session's, else the map's largest id + 1), the service folds it as one-hot scores
    over K classes (the scene their scores give), and the SDK says what K is when a map or a score
    array does not fit it."""
    first, second = frames[0], frames[1]
    h, w = first["rgb"].shape[:2]
    classes = np.zeros((h, w), np.uint8)
    classes[:, w // 2:] = 2  # ids 0 and 2: K = 3
    classes[: h // 4] = 1
    with Client(server.url) as client:
        session = client.create_session(voxel_size=VOXEL)
        session.add_frame(**first, labels=classes)
        assert session.stats()["label_dim"] == 3
        with pytest.raises(ValueError, match=r"^labels: class 4 does not fit K = 3 label classes"):
            session.add_frame(**second, labels=np.where(classes == 2, 4, classes))
        with pytest.raises(ValueError, match=r"^labels: 4 label channels, but this session's labels have K = 3"):
            session.add_frame(**second, labels=np.zeros((h, w, 4), np.float32))
        again = client.session(session.id)  # another handle learns K from the service
        again.add_frame(**second, labels=classes.astype(np.int32))
        view = again.segmentation(first["K"], first["c2w"], w, h)
        drawn = view["labels"][view["alpha"] > 0.5]
        assert set(np.unique(drawn)) <= {0, 1, 2} and len(np.unique(drawn)) == 3
        assert again.stats()["frames"] == 2
        session.delete()

        wide = client.create_session(voxel_size=VOXEL)  # K chosen up front for classes later frames bring
        wide.add_frame(**first, labels=classes, num_classes=6)
        assert wide.stats()["label_dim"] == 6
        # its one labelled frame removed, the session takes any K again: so does this handle
        wide.add_frame(**second)
        wide.remove_frame(0)
        wide.add_frame(**first, labels=classes, num_classes=5)
        assert wide.stats()["label_dim"] == 5
        wide.delete()

        png = io.BytesIO()  # a class map as its PNG file holds it (0 no class, k + 1 class k), with K
        Image.fromarray((classes + 1).astype(np.uint8)).save(png, format="PNG")
        as_png = client.create_session(voxel_size=VOXEL)
        with pytest.raises(ValueError, match="^num_classes: required with a class map PNG"):
            as_png.add_frame(**first, labels=png.getvalue())
        as_png.add_frame(**first, labels=png.getvalue(), num_classes=3)
        as_ids = client.create_session(voxel_size=VOXEL)
        as_ids.add_frame(**first, labels=classes, num_classes=3)
        assert as_png.digest()["sha256"] == as_ids.digest()["sha256"]
        as_png.delete(), as_ids.delete()

        digests = []
        for labels in (classes, np.eye(3, dtype=np.float32)[classes]):  # the map, then its one-hot scores
            session = client.create_session(voxel_size=VOXEL)
            session.add_frame(**first, labels=labels)
            digests.append({k: v for k, v in session.digest().items() if k != "id"})
            session.delete()
        assert digests[0] == digests[1]
