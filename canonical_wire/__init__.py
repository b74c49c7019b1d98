"""The array wire codec shared by the service (``server``) and the SDK (``client``).

It depends on numpy, msgpack and zstandard only (no torch, no ``canonical_core``), so the SDK
stays a thin HTTP client while both ends encode and decode arrays with the same code.

An array travels as a msgpack map ``{"dtype": "uint8"|"uint16"|"float16"|"float32", "shape": [...],
"data": <bytes, little-endian, C order>}``, or with ``"codec": "zstd"`` and ``data`` a zstandard
frame of those bytes (lossless: a sensor's 16-bit depth in a fraction of its bytes and of the CPU
time of a 16-bit PNG).

Example:
    >>> import numpy as np
    >>> a = np.arange(6, dtype=np.uint16).reshape(2, 3)
    >>> b = decode_array(unpack(pack({"a": encode_array(a)}))["a"], "a")
    >>> b.dtype.name, b.tolist()
    ('uint16', [[0, 1, 2], [3, 4, 5]])
"""

from __future__ import annotations

import math

from typing import Literal

import msgpack
import numpy as np
import zstandard

__all__ = ["CODECS", "COLOUR_MODES", "DTYPES", "FLOATS", "IMAGE_FORMATS", "INTEGERS", "NO_LABEL", "WireError", "array_shape",
           "decode_array", "encode_array", "is_array", "pack", "unpack"]

DTYPES = {"uint8": np.dtype("<u1"), "uint16": np.dtype("<u2"), "int16": np.dtype("<i2"), "float16": np.dtype("<f2"),
          "float32": np.dtype("<f4")}
INTEGERS = ("uint8", "uint16", "int16")
FLOATS = ("float16", "float32")
Codec = Literal["raw", "zstd"]
CODECS = ("raw", "zstd")
_KEYS = frozenset({"dtype", "shape", "data"})
# image files a frame's colour may be (as Pillow names them; MPO: a JPEG with the MPF extension, as
# phones write HDR pictures: its first image), and the 8-bit modes of those the service converts to RGB
IMAGE_FORMATS = ("PNG", "JPEG", "MPO")
COLOUR_MODES = ("RGB", "RGBA", "L", "LA", "P", "CMYK", "YCbCr")
NO_LABEL = 65535  # a rendered uint16 label map's pixels that nothing covers (the service writes them, clients read them)
# zstandard's level 1: depth maps pack about as small as at level 3, in less time (the client's CPU
# is often the service's too)
ZSTD_LEVEL = 1


class WireError(ValueError):
    """A message that cannot be decoded; the message starts with the field name.

    ``status`` is the HTTP status it deserves (400 malformed, 413 too large, 422 invalid value) and
    ``code`` the short error code; nothing here knows about HTTP beyond those two attributes.
    """

    def __init__(self, field: str, message: str, status: int = 422, code: str = "invalid_value"):
        super().__init__(f"{field}: {message}")
        self.field, self.status, self.code = field, status, code


# A message holds a few small containers (a frame: its field map, its arrays' maps, a matrix's rows,
# an array's shape): bounded, so that a body of a byte an empty list cannot make a Python object of
# fifty bytes for each of its bytes before anything looks at it
MAX_ITEMS = 64  # entries of one list or map
MAX_CONTAINERS = 1024  # lists and maps in one message
MAX_STR_BYTES = 1 << 20  # one string (a frame_id, a dtype's name); bytes (images, arrays) are not strings


def unpack(body: bytes, field: str = "body") -> dict:
    """A msgpack map from ``body``; WireError(400) naming ``field`` when it is not one, or when it holds
    more than `MAX_CONTAINERS` lists and maps, a list or map of more than `MAX_ITEMS` entries or a
    string of more than `MAX_STR_BYTES`."""
    made = 0

    def counted(container):
        nonlocal made
        made += 1
        if made > MAX_CONTAINERS:
            raise ValueError(f"more than {MAX_CONTAINERS} lists and maps")
        return container

    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=False, max_array_len=MAX_ITEMS, max_map_len=MAX_ITEMS,
                              max_str_len=MAX_STR_BYTES, list_hook=counted, object_hook=counted)
    except Exception as exc:  # msgpack raises several unrelated types for broken input
        raise WireError(field, f"malformed msgpack ({type(exc).__name__}: {exc})", 400, "malformed_body") from None
    if not isinstance(obj, dict):
        raise WireError(field, f"expected a msgpack map, got {type(obj).__name__}", 400, "malformed_body")
    return obj


def pack(obj) -> bytes:
    """msgpack bytes of ``obj`` (bytes travel as msgpack bin)."""
    return msgpack.packb(obj, use_bin_type=True)


def encode_array(a, field: str = "array", codec: Codec = "raw") -> dict:
    """An array map of ``a``, its bytes as they are (``raw``) or zstandard-compressed (``zstd``);
    float64 travels as float32, other dtypes outside `DTYPES` raise ValueError.

    Example:
        >>> m = encode_array(np.zeros((480, 640), np.uint16), codec="zstd")
        >>> m["codec"], len(m["data"]) < 100, decode_array(m).shape
        ('zstd', True, (480, 640))
    """
    a = np.asarray(a)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    name = a.dtype.name
    if name not in DTYPES:
        raise WireError(field, f"dtype {name} cannot travel; use one of {list(DTYPES)}")
    if codec not in CODECS:
        raise ValueError(f"codec: expected one of {list(CODECS)}, got {codec!r}")
    data = np.ascontiguousarray(a, DTYPES[name]).tobytes()
    out = {"dtype": name, "shape": list(a.shape), "data": data}
    if codec == "zstd":
        out["data"], out["codec"] = zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(data), "zstd"
    return out


def is_array(obj) -> bool:
    """Whether ``obj`` has exactly the keys of an array map, ``codec`` optional (values not checked)."""
    return isinstance(obj, dict) and (set(obj) == _KEYS or set(obj) == _KEYS | {"codec"})


MAX_SIDE = 2**31  # an array's sides are below this


def array_shape(obj) -> list[int] | None:
    """The declared shape of an array map when it is a list of ints in 0 .. 2^31 - 1, else None.

    Lets a caller check sizes (pixels, channels) before `decode_array` copies the data. (A side of
    2^62 beside a side of 0 declares no bytes, yet no array can be made of it.)
    """
    if not is_array(obj):
        return None
    shape = obj["shape"]
    if not isinstance(shape, (list, tuple)) or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s < MAX_SIDE
                                                       for s in shape):
        return None
    return list(shape)


def decode_array(obj, field: str = "array", dtypes=tuple(DTYPES), ndim: int | None = None) -> np.ndarray:
    """An owned, writable, native-order numpy array from an array map; WireError(422) naming ``field``.
    A caller checks the declared shape (`array_shape`) before: a small body may declare gigabytes."""
    if not is_array(obj):
        got = sorted(map(str, obj)) if isinstance(obj, dict) else type(obj).__name__
        raise WireError(field, f"expected an array map {{dtype, shape, data}}, got {got}")
    dtype, data = obj["dtype"], obj["data"]
    if not isinstance(dtype, str) or dtype not in dtypes:
        raise WireError(field, f"dtype {dtype!r} is not accepted here; expected one of {list(dtypes)}")
    shape = array_shape(obj)
    if shape is None:
        raise WireError(field, f"shape must be a list of integers in 0 .. {MAX_SIDE - 1}, got {obj['shape']!r}")
    if ndim is not None and len(shape) != ndim:
        raise WireError(field, f"expected {ndim} dimensions, got shape {shape}")
    if not isinstance(data, (bytes, bytearray)):
        raise WireError(field, f"data must be bytes, got {type(data).__name__}")
    expected = math.prod(shape) * DTYPES[dtype].itemsize
    codec = obj.get("codec", "raw")
    if codec == "zstd":
        data = _decompress(data, expected, field)
    elif codec != "raw":
        raise WireError(field, f"codec {codec!r} is not accepted; expected one of {list(CODECS)}")
    if len(data) != expected:
        raise WireError(field, f"data holds {len(data)} bytes; shape {shape} of {dtype} needs {expected}")
    return np.frombuffer(data, DTYPES[dtype]).reshape(shape).astype(DTYPES[dtype].newbyteorder("="), copy=True)


def _decompress(data: bytes, expected: int, field: str) -> bytes:
    """The bytes of a zstandard frame, never more than ``expected`` (the shape's bytes): a small frame
    that would inflate past its declared shape (a decompression bomb) is refused unread."""
    try:
        # a frame that declares its size is decompressed into that many bytes at once: check it first
        declared = zstandard.frame_content_size(data)
        if declared > expected:
            raise WireError(field, f"data inflates to {declared} bytes; shape and dtype need {expected}")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=expected)
    except zstandard.ZstdError as exc:
        raise WireError(field, f"data is not a zstandard frame of at most {expected} bytes ({exc})") from None
    except MemoryError:  # a shape no caller bounded: its bytes cannot be had
        raise WireError(field, f"shape and dtype need {expected} bytes, more than this process can hold", 413,
                        "too_large") from None
