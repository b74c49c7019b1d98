"""The digest that names a frame's wire payload: a retry with the same ``frame_id`` must match it, and
an archived payload is checked against it when read back.

It is taken over the frame *message* rather than its bytes, so that a retry that encodes the same
message otherwise names the same frame: a map's keys in another order (a Go or Rust client's maps
iterate in no fixed order), a multipart upload's parts or its camera JSON's keys in another order
(the service packs them in the order they came), or ``615`` written as ``615.0``. XXH3-128: a
retry check, not a signature (the client names its own frames), fast enough for the acknowledged
path (about 1/50 of BLAKE2b's time on a frame).
"""

from __future__ import annotations

import hashlib
import struct

import msgpack
import xxhash

MESSAGE_PREFIX = "xxh3m:"  # over the message (`payload_digest`)
BYTES_PREFIX = "xxh3:"  # over the bytes, as sessions written before hold (and a payload that is no message)


def _feed(h, value) -> None:
    """``value``'s canonical form into the hash ``h``: maps by sorted key, every number as a float64,
    each item tagged with its kind and length so that no two forms run together."""
    if isinstance(value, dict):
        h.update(b"{%d;" % len(value))
        for key, item in sorted(value.items(), key=lambda kv: (type(kv[0]).__name__, str(kv[0]))):
            _feed(h, key)
            _feed(h, item)
    elif isinstance(value, (list, tuple)):
        h.update(b"[%d;" % len(value))
        for item in value:
            _feed(h, item)
    elif isinstance(value, (bytes, bytearray, memoryview)):
        h.update(b"b%d;" % len(value))
        h.update(value)
    elif isinstance(value, str):
        data = value.encode("utf-8", "surrogatepass")
        h.update(b"s%d;" % len(data))
        h.update(data)
    elif value is None or isinstance(value, bool):
        h.update({None: b"N", True: b"T", False: b"F"}[value])
    elif isinstance(value, (int, float)):
        h.update(b"f" + struct.pack("<d", float(value)))  # 615 and 615.0 alike
    else:  # a msgpack extension type: its code and bytes
        h.update(b"x%d;%d;" % (value.code, len(value.data)))
        h.update(value.data)


def payload_digest(payload: bytes) -> str:
    """The digest naming ``payload``'s frame message (module docstring); a payload that is no msgpack
    map is named by its bytes."""
    try:
        message = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # msgpack raises several unrelated types for broken input
        message = None
    if not isinstance(message, dict):
        return BYTES_PREFIX + xxhash.xxh3_128_hexdigest(payload)
    h = xxhash.xxh3_128()
    _feed(h, message)
    return MESSAGE_PREFIX + h.hexdigest()


def names_payload(digest: str, payload: bytes) -> bool:
    """Whether ``digest`` names ``payload``: a `payload_digest`, or one over its bytes (XXH3 or, as
    sessions written before XXH3 hold, a bare BLAKE2b-128 hex digest)."""
    if digest.startswith(MESSAGE_PREFIX):
        return digest == payload_digest(payload)
    if digest.startswith(BYTES_PREFIX):
        return digest == BYTES_PREFIX + xxhash.xxh3_128_hexdigest(payload)
    return digest == hashlib.blake2b(payload, digest_size=16).hexdigest()
