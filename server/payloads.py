"""A frame's wire payload as the session's frame archive (`server.archive`) keeps it: as it arrived
where its images came compressed, else zstandard over it; read back with a check against its digest."""

from __future__ import annotations

import zlib

import msgpack
import zstandard

from . import wire
from .digests import names_payload

ARCHIVE = "archive.log"  # the file that keeps them

# zstandard's fast levels: -1 packs a 640x480 RGB-D frame of raw arrays as small as level 1 does
# (2.8x) in four fifths of its time, and level 3 takes twice as long for 8 % smaller
ZSTD_LEVEL = -1
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_MSGPACK_MAPS = frozenset(range(0x80, 0x90)) | {0xDE, 0xDF}  # a payload's first byte (a map); zlib's and zstd's differ


def compress_payload(payload: bytes) -> bytes:
    """A frame's wire payload (its packed message) as the archive keeps it, losslessly: as it is when
    its images came compressed (`arrived_compressed`: zstandard over PNG and zstandard bytes gains
    nothing and costs milliseconds a frame), else zstandard over it as it is, so the writer neither
    unpacks nor packs the arrays again."""
    if arrived_compressed(payload):
        return payload
    # with the frame's checksum, so a damaged record is detected when it is read back
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True).compress(payload)


def arrived_compressed(payload: bytes) -> bool:
    """Whether a frame's colour came as PNG/JPEG bytes and its depth (if any) as a PNG or a zstandard
    array: what the SDK and the CLI send by default."""
    msg = msgpack.unpackb(payload, strict_map_key=False)  # a validated frame's payload
    depth = msg.get("depth")
    return isinstance(msg.get("rgb"), bytes) and (depth is None or isinstance(depth, bytes)
                                                  or (isinstance(depth, dict) and depth.get("codec") == "zstd"))


class DamagedFrame(Exception):
    """An archived frame's message does not decompress (or no longer matches its digest): the archive's
    file was damaged."""


def decompress_payload(data: bytes, digest: str | None = None) -> bytes:
    """The wire payload of `compress_payload`'s bytes (of earlier archives: the packed map with its colour
    as PNG, which the wire takes too). Raises `DamagedFrame` when the bytes are not what either wrote,
    or, for a payload kept as it arrived, when they no longer match ``digest`` (its `payload_digest`)."""
    if data[:1] and data[0] in _MSGPACK_MAPS:
        if digest is not None and not names_payload(digest, data):
            raise DamagedFrame(f"{ARCHIVE}: an archived frame no longer matches its digest")
        return data
    try:
        if data[:4] == _ZSTD_MAGIC:
            return zstandard.ZstdDecompressor().decompress(data)
        return zlib.decompress(data)
    except (zstandard.ZstdError, zlib.error) as exc:
        raise DamagedFrame(f"{ARCHIVE}: an archived frame does not decompress ({exc})") from None


def decompress_message(data: bytes, digest: str | None = None) -> dict:
    """The message of `compress_payload`'s bytes, and of the PNG + zlib form of earlier archives. Raises
    `DamagedFrame` when the bytes are not what either wrote (or do not match ``digest``)."""
    return wire.unpack(decompress_payload(data, digest))
