"""Bad input: each case gets the right 4xx, a message naming the field, and leaves the session as it was."""

from __future__ import annotations

import copy
import io
import json

import httpx
import msgpack
import numpy as np
import pytest
from PIL import Image

from client.sdk import encode_array

from .harness import TOKEN, VOXEL, msgpack_frame

AUTH = {"Authorization": f"Bearer {TOKEN}"}
MSGPACK = {**AUTH, "Content-Type": "application/msgpack"}


@pytest.fixture(scope="module")
def target(client, frames):
    session = client.create_session(voxel_size=VOXEL)
    for kwargs in frames[:2]:
        session.add_frame(**kwargs)
    yield session
    session.delete()


def png(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG")
    return buf.getvalue()


class Ctx:
    def __init__(self, url: str, session_id: str, frame: dict):
        self.url, self.sid, self.frame = url, session_id, frame

    def msg(self, **changes) -> dict:
        m = copy.deepcopy(msgpack_frame(self.frame))
        for k, v in changes.items():
            if v is None:
                m.pop(k, None)
            else:
                m[k] = v
        return m

    def post_frame(self, msg=None, body: bytes | None = None, headers=MSGPACK, session_id: str | None = None):
        body = msgpack.packb(msg, use_bin_type=True) if body is None else body
        return httpx.post(f"{self.url}/v1/sessions/{session_id or self.sid}/frames", content=body, headers=headers, timeout=60)

    def multipart(self, files: dict, data: dict):
        return httpx.post(f"{self.url}/v1/sessions/{self.sid}/frames", files=files, data=data, headers=AUTH, timeout=60)

    def view_body(self, **changes) -> dict:
        h, w = self.frame["rgb"].shape[:2]
        body = {"K": self.frame["K"].tolist(), "c2w": self.frame["c2w"].tolist(), "width": w, "height": h, **changes}
        return {k: v for k, v in body.items() if v is not None}

    def get_view(self, route: str = "render", **params):
        """GET .../render (or another view route) with an identity pose, a 32x24 view and ``params`` over them."""
        params = {"pose": ",".join(map(str, np.eye(4).ravel())), "K": "30,30,16,12", "width": 32, "height": 24, **params}
        return httpx.get(f"{self.url}/v1/sessions/{self.sid}/{route}", params=params, headers=AUTH, timeout=60)

    def view(self, route: str = "render", **changes):
        body = json.dumps(self.view_body(**changes))  # NaN passes as the (non-standard) NaN token
        return httpx.post(f"{self.url}/v1/sessions/{self.sid}/{route}", content=body,
                          headers={**AUTH, "Content-Type": "application/json"}, timeout=60)

    def create(self, body=None, content: bytes | None = None):
        if content is not None:
            return httpx.post(f"{self.url}/v1/sessions", content=content, headers={**AUTH, "Content-Type": "application/json"})
        return httpx.post(f"{self.url}/v1/sessions", json=body, headers=AUTH)


EYE = ",".join(map(str, np.eye(4).ravel()))  # an identity pose, GET's form


def _rotated(c2w: np.ndarray, scale: float) -> list:
    t = np.array(c2w, dtype=np.float64)
    t[:3, :3] *= scale
    return t.tolist()


def _nan_pose(c2w: np.ndarray) -> list:
    t = np.array(c2w, dtype=np.float64)
    t[0, 3] = np.nan
    return t.tolist()


def _reflection(c2w: np.ndarray) -> list:
    t = np.array(c2w, dtype=np.float64)
    t[:3, 0] *= -1
    return t.tolist()


def _with_K(K: np.ndarray, **entries) -> list:
    k = np.array(K, dtype=np.float64)
    for (i, j), v in ((( 0, 0), entries.get("fx")), ((0, 2), entries.get("cx"))):
        if v is not None:
            k[i, j] = v
    return k.tolist()


def _classes(c: Ctx) -> np.ndarray:  # a class map PNG's values: 0 no class, k + 1 class k (3 classes)
    return (np.arange(c.frame["rgb"].shape[1]) % 4).astype(np.uint8)[None, :].repeat(c.frame["rgb"].shape[0], 0)


def _jpeg(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="JPEG")
    return buf.getvalue()


def _depth_png(c: Ctx) -> bytes:
    return png(np.round(c.frame["depth"].astype(np.float64) * 1000).astype(np.uint16))


CASES = [
    # (id, request, status, field)
    ("malformed msgpack", lambda c: c.post_frame(body=b"\xc1\x00garbage"), 400, "body"),
    ("msgpack not a map", lambda c: c.post_frame(body=msgpack.packb([1, 2, 3])), 400, "body"),
    ("truncated msgpack", lambda c: c.post_frame(body=msgpack.packb(c.msg(), use_bin_type=True)[:-100]), 400, "body"),
    ("rgb wrong dtype", lambda c: c.post_frame(c.msg(rgb=encode_array(c.frame["rgb"].astype(np.float32)))), 422, "rgb"),
    ("rgb wrong shape", lambda c: c.post_frame(c.msg(rgb=encode_array(np.zeros((240, 320, 4), np.uint8)))), 422, "rgb"),
    # no bytes declared, yet no array can be made of it
    ("rgb side beside an empty one", lambda c: c.post_frame(c.msg(rgb={**encode_array(np.zeros((0, 640, 3), np.uint8)),
                                                                      "shape": [2**62, 0, 3]})), 422, "rgb"),
    ("rgb data length", lambda c: c.post_frame(c.msg(rgb={**encode_array(c.frame["rgb"]), "shape": [240, 321, 3]})), 422, "rgb"),
    ("rgb unknown dtype", lambda c: c.post_frame(c.msg(rgb={**encode_array(c.frame["rgb"]), "dtype": "int8"})), 422, "rgb"),
    ("rgb non-image bytes", lambda c: c.post_frame(c.msg(rgb=b"this is not a png at all")), 422, "rgb"),
    ("depth shape mismatch", lambda c: c.post_frame(c.msg(depth=encode_array(c.frame["depth"][:200]))), 422, "depth"),
    ("depth wrong dtype", lambda c: c.post_frame(c.msg(depth=encode_array(c.frame["depth"].astype(np.uint8)))), 422, "depth"),
    ("depth negative", lambda c: c.post_frame(c.msg(depth=encode_array(-c.frame["depth"]))), 422, "depth"),
    ("depth png without scale", lambda c: c.post_frame(c.msg(depth=_depth_png(c))), 422, "depth_scale"),
    ("depth_scale zero", lambda c: c.post_frame(c.msg(depth=_depth_png(c), depth_scale=0)), 422, "depth_scale"),
    ("depth_scale a string", lambda c: c.post_frame(c.msg(depth=_depth_png(c), depth_scale="mm")), 422, "depth_scale"),
    # a scale near 0 puts every code at an infinite depth
    ("depth_scale overflowing", lambda c: c.post_frame(c.msg(depth=_depth_png(c), depth_scale=1e-300)), 422, "depth_scale"),
    # metres already: the scale would have been ignored, the frame folded at another depth than the client meant
    ("depth_scale with float depth", lambda c: c.post_frame(c.msg(depth_scale=10)), 422, "depth_scale"),
    ("depth png is colour", lambda c: c.post_frame(c.msg(depth=png(c.frame["rgb"]), depth_scale=1000)), 422, "depth"),
    ("c2w NaN", lambda c: c.post_frame(c.msg(c2w=_nan_pose(c.frame["c2w"]))), 422, "c2w"),
    ("c2w not a rotation", lambda c: c.post_frame(c.msg(c2w=_rotated(c.frame["c2w"], 1.1))), 422, "c2w"),
    ("c2w reflection", lambda c: c.post_frame(c.msg(c2w=_reflection(c.frame["c2w"]))), 422, "c2w"),
    ("c2w wrong shape", lambda c: c.post_frame(c.msg(c2w=[[1, 0, 0], [0, 1, 0]])), 422, "c2w"),
    ("c2w not numbers", lambda c: c.post_frame(c.msg(c2w="identity")), 422, "c2w"),
    ("K zero focal", lambda c: c.post_frame(c.msg(K=_with_K(c.frame["K"], fx=0.0))), 422, "K"),
    ("K for another image", lambda c: c.post_frame(c.msg(K=_with_K(c.frame["K"], cx=640.0))), 422, "K"),
    ("declared size mismatch", lambda c: c.post_frame(c.msg(width=640, height=480)), 422, "width"),
    ("declared height mismatch", lambda c: c.post_frame(c.msg(height=c.frame["rgb"].shape[0] + 1)), 422, "height"),
    ("missing c2w", lambda c: c.post_frame(c.msg(c2w=None)), 422, "c2w"),
    ("missing rgb", lambda c: c.post_frame(c.msg(rgb=None)), 422, "rgb"),
    ("unknown frame field", lambda c: c.post_frame(c.msg(dpeth=1)), 422, "dpeth"),
    ("frame_id not a string", lambda c: c.post_frame(c.msg(frame_id=7)), 422, "frame_id"),
    ("frame_id over 256 bytes", lambda c: c.post_frame(c.msg(frame_id="x" * 257)), 422, "frame_id"),
    ("features wrong ndim", lambda c: c.post_frame(c.msg(features=encode_array(np.zeros((4, 4), np.float32)))), 422, "features"),
    # a map with the image's shape turned a quarter ([W', H'] sent as [H', W']) would put values on other pixels
    ("labels transposed", lambda c: c.post_frame(c.msg(labels=encode_array(np.zeros(c.frame["rgb"].shape[1::-1], np.int16)),
                                                       num_classes=2)), 422, "labels"),
    ("labels NaN", lambda c: c.post_frame(c.msg(labels=encode_array(np.full((4, 4, 2), np.nan, np.float32)))), 422, "labels"),
    ("class map without num_classes", lambda c: c.post_frame(c.msg(labels=encode_array(np.zeros((4, 4), np.uint8)))),
     422, "num_classes"),
    ("class map id over K", lambda c: c.post_frame(c.msg(labels=encode_array(np.full((4, 4), 3, np.int16)), num_classes=3)),
     422, "labels"),
    ("class map as floats", lambda c: c.post_frame(c.msg(labels=encode_array(np.zeros((4, 4), np.float32)), num_classes=3)),
     422, "labels"),
    ("num_classes not a count", lambda c: c.post_frame(c.msg(labels=encode_array(np.zeros((4, 4), np.uint8)), num_classes="3")),
     422, "num_classes"),
    ("labels not an array, with num_classes", lambda c: c.post_frame(c.msg(labels="abc", num_classes=3)), 422, "labels"),
    ("num_classes with scores", lambda c: c.post_frame(c.msg(labels=encode_array(np.zeros((4, 4, 2), np.float32)), num_classes=2)),
     422, "num_classes"),
    ("oversize body", lambda c: c.post_frame(body=b"\x00" * (5 * 1024 * 1024)), 413, "body"),
    ("oversize image png", lambda c: c.post_frame(c.msg(rgb=png(np.zeros((1000, 1000, 3), np.uint8)))), 413, "rgb"),
    ("oversize image array", lambda c: c.post_frame(c.msg(rgb={"dtype": "uint8", "shape": [1000, 1000, 3], "data": b""})), 413, "rgb"),
    ("unknown session", lambda c: c.post_frame(c.msg(), session_id="no-such-session"), 404, "session_id"),
    ("wrong content type", lambda c: c.post_frame(c.msg(), headers={**AUTH, "Content-Type": "text/plain"}), 415, "Content-Type"),
    ("no token", lambda c: c.post_frame(c.msg(), headers={"Content-Type": "application/msgpack"}), 401, "Authorization"),
    ("bad token", lambda c: c.post_frame(c.msg(), headers={**MSGPACK, "Authorization": "Bearer nope"}), 401, "Authorization"),
    ("multipart without camera", lambda c: c.multipart({"rgb": ("c.png", png(c.frame["rgb"]), "image/png")}, {}), 422, "camera"),
    ("multipart camera not JSON", lambda c: c.multipart({"rgb": ("c.png", png(c.frame["rgb"]), "image/png")}, {"camera": "{K:"}), 422, "camera"),
    ("multipart class map without num_classes",
     lambda c: c.multipart({"rgb": ("c.png", png(c.frame["rgb"]), "image/png"), "labels": ("l.png", png(_classes(c)), "image/png")},
                           {"camera": json.dumps({"K": c.frame["K"].tolist(), "c2w": c.frame["c2w"].tolist()})}), 422, "num_classes"),
    ("class map png id over K", lambda c: c.post_frame(c.msg(labels=png(_classes(c) + 3), num_classes=3)), 422, "labels"),
    ("class map as colour png", lambda c: c.post_frame(c.msg(labels=png(c.frame["rgb"]), num_classes=3)), 422, "labels"),
    ("class map as jpeg", lambda c: c.post_frame(c.msg(labels=_jpeg(_classes(c)), num_classes=3)), 422, "labels"),
    ("multipart unknown part", lambda c: c.multipart({"rgb": ("c.png", png(c.frame["rgb"]), "image/png")},
                                                     {"camera": json.dumps({"K": c.frame["K"].tolist()}), "extra": "1"}), 422, "extra"),
    ("render NaN pose", lambda c: c.view(c2w=_nan_pose(c.frame["c2w"])), 422, "c2w"),
    ("render zero focal", lambda c: c.view(K=_with_K(c.frame["K"], fx=0.0)), 422, "K"),
    ("render too large", lambda c: c.view(width=4000, height=4000), 413, "width"),
    ("render negative width", lambda c: c.view(width=-3), 422, "width"),
    ("render missing K", lambda c: c.view(K=None), 422, "K"),
    ("render background above 1", lambda c: c.view(background=[2, 2, 2]), 422, "background.0"),
    ("render background NaN", lambda c: c.view(background=[float("nan"), 0, 0]), 422, "background.0"),
    ("render GET background NaN", lambda c: c.get_view(background="nan,0,0"), 422, "background"),
    ("render GET background above 1", lambda c: c.get_view(background="2,2,2"), 422, "background"),
    ("render GET pose of infinities", lambda c: c.get_view(pose=",".join(["1e400", "0", "0", "0"] * 4)), 422, "pose"),
    ("render background shape", lambda c: c.view(background=[1, 1]), 422, "background"),
    ("render unknown colour mode", lambda c: c.view(colour="premultiplied"), 422, "colour"),
    ("render unknown depth mode", lambda c: c.view(depth="mean"), 422, "depth"),
    ("render GET unknown depth mode", lambda c: c.get_view(depth="mean"), 422, "depth"),
    ("render GET unknown colour mode", lambda c: c.get_view(colour="bright"), 422, "colour"),
    ("features bad preview", lambda c: httpx.post(f"{c.url}/v1/sessions/{c.sid}/features?preview=jpg",
                                                  json=c.view_body(), headers=AUTH), 422, "preview"),
    ("render GET bad pose", lambda c: c.get_view(pose="1,0,0"), 422, "pose"),
    # valid views within max_image_pixels, over what the picture's format holds a side
    ("image jpeg wider than JPEG holds", lambda c: c.get_view("image", format="jpeg", width=65501, height=1, pose=EYE,
                                                              K="300,300,32750,0.5"), 422, "width"),
    ("image webp taller than WebP holds", lambda c: c.get_view("image", format="webp", width=1, height=16384, pose=EYE,
                                                               K="300,300,0.5,8192"), 422, "height"),
    ("segmentation without labels", lambda c: c.view("segmentation"), 409, "labels"),
    ("create unknown setting", lambda c: c.create({"voxel_size": 0.01, "voxle_size": 0.02}), 422, "voxle_size"),
    ("create voxel_size zero", lambda c: c.create({"voxel_size": 0}), 422, "voxel_size"),
    ("create voxel_size negative", lambda c: c.create({"voxel_size": -0.01}), 422, "voxel_size"),
    ("create unknown sensor family", lambda c: c.create({"sensor": {"family": "sonar"}}), 422, "sensor.family"),
    ("create bad weighting", lambda c: c.create({"voxel_size": 0.01, "weighting": "median"}), 422, "weighting"),
    ("create near above far", lambda c: c.create({"voxel_size": 0.01, "range": {"near": 5, "far": 1}}), 422, "range.near"),
    ("create completion radius zero", lambda c: c.create({"voxel_size": 0.01, "depth": {"completion_radius": 0}}), 422,
     "depth.completion_radius"),
    ("create opacity_bias not a number", lambda c: c.create({"voxel_size": 0.01, "decoder": {"opacity_bias": "high"}}), 422,
     "decoder.opacity_bias"),
    ("create opacity_slope zero", lambda c: c.create({"voxel_size": 0.01, "decoder": {"opacity_slope": 0}}), 422,
     "decoder.opacity_slope"),
    ("create malformed JSON", lambda c: c.create(content=b"{voxel_size: 1"), 400, "body"),
    # curl's default for -d: the JSON object is there, under another type
    ("create form-encoded", lambda c: httpx.post(f"{c.url}/v1/sessions", content=b'{"voxel_size": 0.01}',
                                                 headers={**AUTH, "Content-Type": "application/x-www-form-urlencoded"}),
     415, "Content-Type"),
    ("render GET pose not a rotation", lambda c: c.get_view(pose=",".join(["0"] * 15 + ["1"])), 422, "pose"),
    # JSON carries lone surrogates (escaped), which no text holds: named back, never a codec's message
    ("multipart frame_id lone surrogate",
     lambda c: c.multipart({"rgb": ("c.png", png(c.frame["rgb"]), "image/png")},
                           {"camera": json.dumps({"K": c.frame["K"].tolist(), "c2w": c.frame["c2w"].tolist(),
                                                  "frame_id": "a\ud800"})}), 422, "frame_id"),
    ("poses key lone surrogate", lambda c: httpx.post(f"{c.url}/v1/sessions/{c.sid}/poses", content=b'{"remove": ["\\ud800"]}',
                                                      headers={**AUTH, "Content-Type": "application/json"}), 422, "frames.\ud800"),
]


def _state(session) -> tuple:
    stats, digest = session.stats(), session.digest()
    return stats["frames"], stats["voxels"], stats["disk_bytes"], stats["gaussians"], digest["sha256"]


@pytest.mark.realdata
@pytest.mark.parametrize("make, status, field", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input(server, client, target, frames, make, status, field):
    before = _state(target)
    sessions_before = len(client.sessions())
    r = make(Ctx(server.url, target.id, frames[2]))
    assert r.status_code == status, r.text
    error = r.json()["error"]
    assert error["field"] == field, error
    assert field in error["message"] and error["code"]
    assert _state(target) == before
    assert len(client.sessions()) == sessions_before


@pytest.mark.realdata
def test_capacity_409_leaves_session_and_log_unchanged(client, frames):
    session = client.create_session(voxel_size=VOXEL, max_voxels=6000)
    session.add_frame(**frames[0])
    before = _state(session)
    r = httpx.post(f"{client._http.base_url}/v1/sessions/{session.id}/frames", headers=MSGPACK,
                   content=msgpack.packb(msgpack_frame(frames[1]), use_bin_type=True))
    assert r.status_code == 409, r.text
    assert r.json()["error"]["field"] == "max_voxels" and "max_voxels" in r.json()["error"]["message"]
    assert _state(session) == before  # the log record was cut off again (disk_bytes unchanged)
    session.delete()


def test_too_many_sessions_409(server, client):
    created = []
    try:
        for _ in range(25):
            r = httpx.post(f"{server.url}/v1/sessions", json={"voxel_size": 0.05}, headers=AUTH)
            if r.status_code != 201:
                break
            created.append(r.json()["id"])
        assert r.status_code == 409 and r.json()["error"]["field"] == "max_sessions"
    finally:
        for sid in created:
            httpx.delete(f"{server.url}/v1/sessions/{sid}", headers=AUTH)


def test_unknown_route_and_method(server):
    r = httpx.get(f"{server.url}/v1/nothing", headers=AUTH)
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    r = httpx.put(f"{server.url}/v1/sessions", headers=AUTH)
    assert r.status_code == 405 and r.json()["error"]["field"] == "method"


@pytest.mark.realdata
def test_fold_time_error_leaves_log_unchanged(client, frames):
    """A frame that passes decoding but fails inside the fold (here: a client-features session sent a
    frame without features) is logged first, then cut off again: the session and its files are as before."""
    session = client.create_session(voxel_size=VOXEL, features={"backend": "client", "dim": 8})
    kwargs = frames[0]
    h, w = kwargs["rgb"].shape[:2]
    feats = np.random.default_rng(0).standard_normal((h // 4, w // 4, 12)).astype(np.float16)
    session.add_frame(**kwargs, features=feats)
    before = _state(session)
    r = httpx.post(f"{client._http.base_url}/v1/sessions/{session.id}/frames", headers=MSGPACK,
                   content=msgpack.packb(msgpack_frame(frames[1]), use_bin_type=True))
    assert r.status_code == 422 and r.json()["error"]["field"] == "features", r.text
    assert _state(session) == before
    session.add_frame(**frames[1], features=feats)
    assert session.stats()["frames"] == 2
    session.delete()


# values of every kind a field may be given by mistake: wrong types, out of range, non-finite, empty
_WRONG = [None, "x", "", 0, -1, 1.5, float("nan"), float("inf"), 2**63 - 1, True, [], {}, [[]], [[1, 2], [3]], b"",
          b"\x89PNG\r\n\x1a\n", [[float("nan")] * 3] * 3, [[0.0] * 3] * 3, {"dtype": "float32", "shape": [-1], "data": b""},
          {"dtype": "float32", "shape": [2**31, 2**31], "data": b""},
          {"dtype": "float32", "shape": [3, 3], "data": b"\x28\xb5\x2f\xfd" + b"\xff" * 20, "codec": "zstd"}]


def _mutated(rnd, base: dict) -> dict:
    """``base`` with one to three of its fields (or an optional or unknown one) set wrong, removed,
    given another image, cut short, or with bytes overwritten."""
    m = copy.deepcopy(base)
    for _ in range(rnd.randint(1, 3)):
        key = rnd.choice([*m, "depth_scale", "depth_std", "features", "labels", "num_classes", "frame_id", "extra"])
        value, op = m.get(key), rnd.random()
        if op < 0.4:
            m[key] = copy.deepcopy(rnd.choice(_WRONG))
        elif op < 0.5:
            m.pop(key, None)
        elif isinstance(value, (bytes, bytearray)) and value:
            data = bytearray(value)
            if op < 0.75:
                data = data[: rnd.randrange(len(data))]
            else:
                for _ in range(rnd.randint(1, 20)):
                    data[rnd.randrange(len(data))] = rnd.randrange(256)
            m[key] = bytes(data)
        elif isinstance(value, dict):
            value[rnd.choice(["dtype", "shape", "data", "codec"])] = copy.deepcopy(rnd.choice(_WRONG + [[240, 320], "uint16"]))
        elif key in ("K", "c2w") and isinstance(value, list) and value and all(isinstance(r, list) and r for r in value):
            row = value[rnd.randrange(len(value))]
            row[rnd.randrange(len(row))] = rnd.choice([0.0, -1.0, 1e9, float("nan"), 5.0])
        else:
            m[key] = rnd.choice([1e-300, 1e300, 1000.0, 65535, "id" * rnd.randint(1, 200)])
    return m


@pytest.mark.realdata
def test_mutated_frames_are_refused_naming_a_field_or_folded_and_refusals_change_nothing(server, client, frames):
    """Seeded random mutations of a real frame message (the SDK's, compact: PNG colour, zstd depth):
    every answer is a fold or a 4xx naming a field, never a 5xx; and the refused ones leave nothing:
    the session ends as a second one fed only the accepted messages, bit for bit."""
    import random

    from client.sdk.frames import frame_body

    rnd = random.Random(0)
    fuzzed, accepted_only = client.create_session(voxel_size=VOXEL), client.create_session(voxel_size=VOXEL)
    try:
        base = msgpack.unpackb(frame_body(**{k: frames[0][k] for k in ("rgb", "K", "c2w", "depth")}), raw=False)
        accepted = []
        for _ in range(120):
            body = msgpack.packb(_mutated(rnd, base), use_bin_type=True)
            r = httpx.post(f"{server.url}/v1/sessions/{fuzzed.id}/frames", content=body, headers=MSGPACK, timeout=60)
            assert r.status_code < 500, r.text
            if r.status_code == 200:
                accepted.append(body)
            else:
                assert 400 <= r.status_code < 500 and r.json()["error"]["field"], r.text
        assert 0 < len(accepted) < 120  # both kinds of answer were exercised
        for body in accepted:
            r = httpx.post(f"{server.url}/v1/sessions/{accepted_only.id}/frames", content=body, headers=MSGPACK, timeout=60)
            assert r.status_code == 200, r.text
        assert fuzzed.stats()["frames"] == len(accepted)
        assert fuzzed.digest()["sha256"] == accepted_only.digest()["sha256"]
    finally:
        fuzzed.delete()
        accepted_only.delete()


@pytest.mark.realdata
def test_a_class_map_png_over_K_is_told_in_its_own_values(server, target, frames):
    """A PNG holds 0 for no class and k + 1 for class k: a value past K is named as written, not as
    the class id it stands for (which read as an off-by-one)."""
    c = Ctx(server.url, target.id, frames[2])
    r = c.post_frame(c.msg(labels=png((_classes(c) + 2).astype(np.uint8)), num_classes=4))  # values 2..5
    assert r.status_code == 422 and "PNG value 5 (class 4) does not fit num_classes = 4" in r.json()["error"]["message"], r.text
