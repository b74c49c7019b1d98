"""The array wire codec shared by the service (``server``) and the SDK (``client``).

It depends on numpy and msgpack only (no torch, no ``canonical_core``), so the SDK stays a thin
HTTP client while both ends encode and decode arrays with the same code.

An array travels as a msgpack map ``{"dtype": "uint8"|"uint16"|"float16"|"float32", "shape": [...],
"data": <bytes, little-endian, C order>}``.

Example:
    >>> import numpy as np
    >>> a = np.arange(6, dtype=np.uint16).reshape(2, 3)
    >>> b = decode_array(unpack(pack({"a": encode_array(a)}))["a"], "a")
    >>> b.dtype.name, b.tolist()
    ('uint16', [[0, 1, 2], [3, 4, 5]])
"""

from __future__ import annotations

import math

import msgpack
import numpy as np

__all__ = ["DTYPES", "FLOATS", "WireError", "array_shape", "decode_array", "encode_array", "is_array", "pack", "unpack"]

DTYPES = {"uint8": np.dtype("<u1"), "uint16": np.dtype("<u2"), "float16": np.dtype("<f2"), "float32": np.dtype("<f4")}
FLOATS = ("float16", "float32")


class WireError(ValueError):
    """A message that cannot be decoded; the message starts with the field name.

    ``status`` is the HTTP status it deserves (400 malformed, 413 too large, 422 invalid value) and
    ``code`` the short error code; nothing here knows about HTTP beyond those two attributes.
    """

    def __init__(self, field: str, message: str, status: int = 422, code: str = "invalid_value"):
        super().__init__(f"{field}: {message}")
        self.field, self.status, self.code = field, status, code


def unpack(body: bytes, field: str = "body") -> dict:
    """A msgpack map from ``body``; WireError(400) naming ``field`` when it is not one."""
    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for broken input
        raise WireError(field, f"malformed msgpack ({type(exc).__name__}: {exc})", 400, "malformed_body") from None
    if not isinstance(obj, dict):
        raise WireError(field, f"expected a msgpack map, got {type(obj).__name__}", 400, "malformed_body")
    return obj


def pack(obj) -> bytes:
    """msgpack bytes of ``obj`` (bytes travel as msgpack bin)."""
    return msgpack.packb(obj, use_bin_type=True)


def encode_array(a, field: str = "array") -> dict:
    """An array map of ``a``; float64 travels as float32, other dtypes outside `DTYPES` raise ValueError."""
    a = np.asarray(a)
    if a.dtype == np.float64:
        a = a.astype(np.float32)
    name = a.dtype.name
    if name not in DTYPES:
        raise WireError(field, f"dtype {name} cannot travel; use one of {list(DTYPES)}")
    return {"dtype": name, "shape": list(a.shape), "data": np.ascontiguousarray(a, DTYPES[name]).tobytes()}


def is_array(obj) -> bool:
    """Whether ``obj`` has exactly the keys of an array map (its values are not checked)."""
    return isinstance(obj, dict) and set(obj) == {"dtype", "shape", "data"}


def array_shape(obj) -> list[int] | None:
    """The declared shape of an array map when it is a list of non-negative ints, else None.

    Lets a caller check sizes (pixels, channels) before `decode_array` copies the data.
    """
    if not is_array(obj):
        return None
    shape = obj["shape"]
    if not isinstance(shape, (list, tuple)) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        return None
    return list(shape)


def decode_array(obj, field: str = "array", dtypes=tuple(DTYPES), ndim: int | None = None) -> np.ndarray:
    """An owned, writable, native-order numpy array from an array map; WireError(422) naming ``field``."""
    if not is_array(obj):
        got = sorted(map(str, obj)) if isinstance(obj, dict) else type(obj).__name__
        raise WireError(field, f"expected an array map {{dtype, shape, data}}, got {got}")
    dtype, data = obj["dtype"], obj["data"]
    if not isinstance(dtype, str) or dtype not in dtypes:
        raise WireError(field, f"dtype {dtype!r} is not accepted here; expected one of {list(dtypes)}")
    shape = array_shape(obj)
    if shape is None:
        raise WireError(field, f"shape must be a list of non-negative integers, got {obj['shape']!r}")
    if ndim is not None and len(shape) != ndim:
        raise WireError(field, f"expected {ndim} dimensions, got shape {shape}")
    if not isinstance(data, (bytes, bytearray)):
        raise WireError(field, f"data must be bytes, got {type(data).__name__}")
    expected = math.prod(shape) * DTYPES[dtype].itemsize
    if len(data) != expected:
        raise WireError(field, f"data holds {len(data)} bytes; shape {shape} of {dtype} needs {expected}")
    return np.frombuffer(data, DTYPES[dtype]).reshape(shape).astype(DTYPES[dtype].newbyteorder("="), copy=True)
