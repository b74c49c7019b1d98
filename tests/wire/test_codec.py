"""The shared array codec: round trips of every dtype and shape it carries, and every error path."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from canonical_wire import DTYPES, WireError, array_shape, decode_array, encode_array, is_array, pack, unpack

REPO = Path(__file__).resolve().parents[2]
SHAPES = [(), (0,), (5,), (2, 3), (3, 0, 2), (2, 3, 4), (1, 2, 1, 3)]


@pytest.mark.parametrize("dtype", list(DTYPES))
@pytest.mark.parametrize("shape", SHAPES, ids=str)
def test_round_trip_every_dtype_and_shape(dtype, shape):
    rng = np.random.default_rng(len(shape))
    a = (rng.random(shape) * (200 if dtype.startswith("uint") else 1)).astype(dtype)
    obj = unpack(pack({"a": encode_array(a)}))["a"]  # through msgpack bytes, as on the wire
    assert obj["dtype"] == dtype and obj["shape"] == list(shape)
    b = decode_array(obj, "a")
    assert b.dtype == np.dtype(dtype) and b.shape == shape and np.array_equal(a, b)
    assert b.flags.writeable and b.flags.owndata  # an owned copy, not a view of the message


def test_extremes_survive_bit_exact():
    for a in (np.array([0, 255], np.uint8), np.array([0, 65535], np.uint16),
              np.array([np.inf, -np.inf, 65504, -0.0], np.float16),
              np.array([np.finfo(np.float32).max, np.finfo(np.float32).tiny, -0.0], np.float32)):
        b = decode_array(encode_array(a), "x")
        assert b.tobytes() == a.tobytes()
    nan = decode_array(encode_array(np.array([np.nan], np.float32)), "x")
    assert np.isnan(nan).all()


def test_data_is_little_endian_c_order():
    a = np.arange(6, dtype=">u2").reshape(2, 3).T  # big-endian and not C-contiguous
    obj = encode_array(a)
    assert obj["dtype"] == "uint16" and obj["shape"] == [3, 2]
    assert obj["data"] == np.ascontiguousarray(a, "<u2").tobytes()
    assert np.array_equal(decode_array(obj, "a"), a)


def test_float64_travels_as_float32():
    obj = encode_array(np.array([1.5, 2.25]))
    assert obj["dtype"] == "float32" and decode_array(obj, "x").tolist() == [1.5, 2.25]


@pytest.mark.parametrize("dtype", [np.int64, np.int8, np.bool_, np.complex64, object])
def test_encode_refuses_other_dtypes(dtype):
    with pytest.raises(WireError, match=r"^depth: dtype .* cannot travel") as info:
        encode_array(np.zeros(2, dtype), "depth")
    assert info.value.field == "depth" and info.value.status == 422


def _good() -> dict:
    return encode_array(np.zeros((2, 3), np.float32))


DECODE_ERRORS = [
    ("not a map", lambda: [1, 2], {}, "expected an array map"),
    ("missing data", lambda: {"dtype": "uint8", "shape": [1]}, {}, "expected an array map"),
    ("extra key", lambda: {**_good(), "order": "C"}, {}, "expected an array map"),
    ("unknown dtype", lambda: {**_good(), "dtype": "int8"}, {}, "dtype 'int8' is not accepted"),
    ("dtype not a string", lambda: {**_good(), "dtype": 4}, {}, "dtype 4 is not accepted"),
    ("dtype not allowed here", lambda: _good(), {"dtypes": ("uint8",)}, "dtype 'float32' is not accepted here"),
    ("shape not a list", lambda: {**_good(), "shape": "2x3"}, {}, "shape must be a list"),
    ("shape negative", lambda: {**_good(), "shape": [-2, -3]}, {}, "shape must be a list"),
    ("shape of floats", lambda: {**_good(), "shape": [2.0, 3.0]}, {}, "shape must be a list"),
    ("shape of booleans", lambda: {**_good(), "shape": [True, 6]}, {}, "shape must be a list"),
    ("wrong ndim", lambda: _good(), {"ndim": 3}, "expected 3 dimensions, got shape [2, 3]"),
    ("data not bytes", lambda: {**_good(), "data": "0000"}, {}, "data must be bytes"),
    ("data too short", lambda: {**_good(), "data": _good()["data"][:-1]}, {}, "data holds 23 bytes; shape [2, 3] of float32 needs 24"),
    ("data too long", lambda: {**_good(), "shape": [2, 2]}, {}, "data holds 24 bytes; shape [2, 2] of float32 needs 16"),
]


@pytest.mark.parametrize("make, kwargs, message", [c[1:] for c in DECODE_ERRORS], ids=[c[0] for c in DECODE_ERRORS])
def test_decode_errors_name_the_field(make, kwargs, message):
    with pytest.raises(WireError) as info:
        decode_array(make(), "features", **kwargs)
    err = info.value
    assert str(err).startswith("features: ") and message in str(err)
    assert err.field == "features" and err.status == 422 and err.code == "invalid_value"
    assert isinstance(err, ValueError)


@pytest.mark.parametrize("body, message", [(b"\xc1", "malformed msgpack"), (msgpack.packb([1, 2]), "expected a msgpack map"),
                                           (pack({"a": 1})[:-1], "malformed msgpack"), (b"", "malformed msgpack")])
def test_unpack_errors_are_400(body, message):
    with pytest.raises(WireError, match=f"^body: {message}") as info:
        unpack(body)
    assert info.value.status == 400 and info.value.code == "malformed_body"


def test_is_array_and_array_shape():
    assert is_array(_good()) and not is_array({"dtype": "uint8"}) and not is_array([1])
    assert array_shape(_good()) == [2, 3]
    assert array_shape({**_good(), "shape": [2, -1]}) is None and array_shape("x") is None


def test_sdk_and_server_share_the_codec_and_the_sdk_imports_no_torch():
    import client.sdk
    import server.wire

    for name in ("encode_array", "decode_array", "pack", "unpack"):
        assert getattr(client.sdk, name) is getattr(server.wire, name)
    code = ("import sys, client.sdk, canonical_wire; "
            "bad = [m for m in ('torch', 'canonical_core', 'server') if m in sys.modules]; "
            "sys.exit(f'imported {bad}' if bad else 0)")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, timeout=60)


def test_docstring_example_runs():
    import doctest

    import canonical_wire

    result = doctest.testmod(canonical_wire, verbose=False)
    assert result.attempted > 0 and result.failed == 0


@pytest.mark.parametrize("dtype", list(DTYPES))
def test_zstd_round_trip_is_exact_and_smaller_for_depth(dtype):
    rng = np.random.default_rng(7)
    a = (rng.random((48, 64)) * (60000 if dtype == "uint16" else 200 if dtype == "uint8" else 1)).astype(dtype)
    obj = unpack(pack({"a": encode_array(a, "a", codec="zstd")}))["a"]
    assert obj["codec"] == "zstd" and is_array(obj) and array_shape(obj) == [48, 64]
    b = decode_array(obj, "a")
    assert b.dtype == a.dtype and b.tobytes() == a.tobytes()
    depth = np.where(rng.random((480, 640)) < 0.6, 0, 400 + np.arange(640)[None, :] // 8).astype(np.uint16)  # sensor-like
    assert len(encode_array(depth, codec="zstd")["data"]) < depth.nbytes / 4


def test_zstd_frames_that_inflate_past_their_shape_are_refused_unread():
    import zstandard

    obj = encode_array(np.zeros((4, 4), np.uint16), codec="zstd")
    declared = {**obj, "data": zstandard.ZstdCompressor().compress(bytes(1 << 24))}  # says 16 MiB in its header
    with pytest.raises(WireError, match=r"^d: data inflates to 16777216 bytes; shape and dtype need 32") as info:
        decode_array(declared, "d")
    assert info.value.status == 422
    undeclared = {**obj, "data": zstandard.ZstdCompressor(write_content_size=False).compress(bytes(1 << 24))}
    with pytest.raises(WireError, match=r"^d: data is not a zstandard frame of at most 32 bytes"):
        decode_array(undeclared, "d")
    short = {**obj, "data": zstandard.ZstdCompressor().compress(bytes(30))}
    with pytest.raises(WireError, match=r"^d: data holds 30 bytes; shape \[4, 4\] of uint16 needs 32"):
        decode_array(short, "d")
    with pytest.raises(WireError, match="^d: data is not a zstandard frame"):
        decode_array({**obj, "data": b"not zstd"}, "d")
    with pytest.raises(WireError, match=r"^d: codec 'lz4' is not accepted; expected one of \['raw', 'zstd'\]"):
        decode_array({**obj, "codec": "lz4"}, "d")
    with pytest.raises(ValueError, match="^codec: expected one of"):
        encode_array(np.zeros(3, np.uint8), codec="png")
