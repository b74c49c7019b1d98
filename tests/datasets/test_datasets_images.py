"""Image decoding: libpng's fast path (`png_pixels`) held to Pillow's decode, the reference, on every
real capture and on every PNG layout; the loaders and the service's wire decode give Pillow's pixels
whichever path decodes them, and their errors for broken files are Pillow's."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
from PIL import Image

from canonical_core.datasets.images import png_pixels, read_depth, read_rgb
from server.wire import WireError, decode_depth_png, decode_rgb

from ..conftest import DATA, require_capture

# every real capture's PNG colour and depth files (a few frames each), with Pillow's mode for them
CAPTURES = ("realsense_shelf", "sun3d_studyroom", "hololens_office", "apc_bins/bin_labels", "apc_bins/bin_mask",
            "livingroom_synthetic", "slambook_rgbd5")


def _capture_pngs(name: str) -> list[Path]:
    root = require_capture(DATA / name)
    files = sorted(root.rglob("*.png"))
    step = max(1, len(files) // 6)
    return files[::step] + files[1::step]  # a dozen a capture: both offsets, where colour and depth files alternate


def _pillow(data: bytes) -> np.ndarray:  # the reference: Pillow's own decode
    return np.array(Image.open(io.BytesIO(data)))


def _png(array: np.ndarray, **params) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, format="PNG", **params)
    return buf.getvalue()


@pytest.mark.parametrize("name", CAPTURES)
def test_libpng_decodes_every_captures_colour_and_depth_as_pillow_does(name):
    decoded = 0
    for path in _capture_pngs(name):
        data = path.read_bytes()
        image = Image.open(io.BytesIO(data))
        pixels = png_pixels(image, data)
        if image.mode in ("RGB", "I;16"):  # the layouts cameras write: the fast path must take them
            assert pixels is not None, f"{path}: {image.mode} not decoded by libpng"
            reference = _pillow(data)
            assert pixels.dtype == reference.dtype and np.array_equal(pixels, reference), path
            decoded += 1
        else:
            assert pixels is None, path
    assert decoded > 0


def test_the_loaders_and_the_wire_give_pillows_pixels_on_a_real_frame(shelf_path):
    color, depth = shelf_path / "frames" / "frame-000015.color.png", shelf_path / "frames" / "frame-000015.depth.png"
    reference_rgb = _pillow(color.read_bytes())
    reference_metres = _pillow(depth.read_bytes()).astype(np.float64) / 1000.0
    reference_metres[reference_metres == 65.535] = 0.0
    for rgb in (read_rgb(color), decode_rgb(color.read_bytes())):
        assert rgb.dtype == np.uint8 and np.array_equal(rgb, reference_rgb)
    for metres in (read_depth(depth, 1000.0), decode_depth_png(depth.read_bytes(), 1000.0)):
        assert metres.dtype == np.float32
        assert np.array_equal(metres, reference_metres.astype(np.float32))
    assert read_rgb(color).flags.writeable  # torch warns on read-only arrays


# Adam7's passes: (first column, first row, column step, row step)
ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _interlaced_png(array: np.ndarray) -> bytes:  # 8-bit RGB or 16-bit grey; Pillow writes no interlaced PNG
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    height, width = array.shape[:2]
    colour_type, bits = (2, 8) if array.ndim == 3 else (0, 16)
    samples = array.astype(">u2") if bits == 16 else array
    rows = b"".join(b"\0" + row.tobytes() for x0, y0, dx, dy in ADAM7 for row in samples[y0::dy, x0::dx] if row.size)
    header = struct.pack(">IIBBBBB", width, height, bits, colour_type, 0, 0, 1)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


rng = np.random.default_rng(0)
COLOUR = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
LAYOUTS = {  # name -> (PNG bytes, whether libpng takes it)
    "8-bit RGB": (_png(COLOUR), True),
    "8-bit RGB, zlib level 0": (_png(COLOUR, compress_level=0), True),
    "8-bit RGB with a transparent colour": (_png(COLOUR, transparency=tuple(int(v) for v in COLOUR[0, 0])), False),
    "RGBA": (_png(np.dstack([COLOUR, COLOUR[..., :1]])), False),
    "grey": (_png(COLOUR[..., 0]), False),
    "grey and alpha": (_png(np.dstack([COLOUR[..., 0], COLOUR[..., 1]]), ), False),
    "palette": (_png(np.asarray(Image.fromarray(COLOUR).convert("P"))), False),
    "16-bit RGB": (imagecodecs.png_encode(COLOUR.astype(np.uint16) * 257), False),
    "8-bit RGB, interlaced": (_interlaced_png(COLOUR), False),
}


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_every_colour_layout_reads_as_pillow_converts_it(layout, tmp_path):
    data, fast = LAYOUTS[layout]
    image = Image.open(io.BytesIO(data))
    assert (png_pixels(image, data) is not None) == fast, image.mode
    reference = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    path = tmp_path / "c.png"
    path.write_bytes(data)
    for rgb in (read_rgb(path), decode_rgb(data)):
        assert rgb.shape == (7, 5, 3) and rgb.dtype == np.uint8 and np.array_equal(rgb, reference)


@pytest.mark.parametrize("interlaced", [False, True])
def test_16_bit_depth_reads_as_pillow_decodes_it(interlaced, tmp_path):
    raw = rng.integers(0, 65536, (6, 9), dtype=np.uint16)
    raw[0, 0], raw[0, 1] = 0, 65535  # missing, both ways
    data = _interlaced_png(raw) if interlaced else _png(raw)
    image = Image.open(io.BytesIO(data))
    assert image.mode == "I;16" and (png_pixels(image, data) is None) == interlaced
    assert np.array_equal(_pillow(data), raw)
    path = tmp_path / "d.png"
    path.write_bytes(data)
    expected = np.where((raw == 0) | (raw == 65535), 0.0, raw / 5000.0).astype(np.float32)
    for metres in (read_depth(path, 5000.0), decode_depth_png(data, 5000.0)):
        assert np.array_equal(metres, expected)


def _broken(data: bytes) -> dict[str, bytes]:
    flipped = bytearray(data)
    flipped[len(data) // 2: len(data) // 2 + 64] = bytes(64)  # zeroed compressed data: the CRC and the stream fail
    return {"truncated": data[: len(data) // 2], "zeroed": bytes(flipped)}


@pytest.mark.parametrize("damage", ["truncated", "zeroed"])
def test_a_broken_png_fails_as_libpng_says_naming_the_file_or_field(damage, tmp_path):
    colour = _broken(_png(rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)))[damage]
    depth = _broken(_png(rng.integers(1, 60000, (64, 64), dtype=np.uint16)))[damage]
    for data in (colour, depth):
        with pytest.raises(ValueError, match="^libpng: "):
            png_pixels(Image.open(io.BytesIO(data)), data)
    (tmp_path / "c.png").write_bytes(colour)
    (tmp_path / "d.png").write_bytes(depth)
    with pytest.raises(ValueError, match=r"c\.png: unreadable image"):
        read_rgb(tmp_path / "c.png")
    with pytest.raises(ValueError, match=r"d\.png: unreadable image"):
        read_depth(tmp_path / "d.png", 1000.0)
    with pytest.raises(WireError, match="corrupt PNG image") as err:
        decode_rgb(colour)
    assert err.value.field == "rgb"
    with pytest.raises(WireError, match="corrupt PNG image") as err:
        decode_depth_png(depth, 1000.0)
    assert err.value.field == "depth"


def test_a_png_whose_data_stream_ends_before_its_last_row_is_refused(tmp_path):
    """A complete compressed stream that holds fewer rows than the header says: libpng refuses it
    where Pillow would fill the missing rows with black."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    rows = b"".join(b"\x00" + bytes(range(48)) for _ in range(4))  # 4 of the 16 rows the header says
    data = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 16, 16, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    assert Image.open(io.BytesIO(data)).convert("RGB").size == (16, 16)  # Pillow takes it
    (tmp_path / "short.png").write_bytes(data)
    with pytest.raises(ValueError, match=r"short\.png: unreadable image \(libpng: Not enough image data\)"):
        read_rgb(tmp_path / "short.png")
    with pytest.raises(WireError, match=r"corrupt PNG image \(libpng: Not enough image data\)") as err:
        decode_rgb(data)
    assert err.value.field == "rgb"


def test_the_sdks_and_the_services_png_encoders_round_trip_and_pack_as_small_as_pillows_fast_level(shelf_path):
    from client.sdk import encode_png as sdk_png
    from server.wire import encode_png as service_png

    frame = read_rgb(shelf_path / "frames" / "frame-000015.color.png")
    grey = frame[..., 1].copy()
    for encode in (sdk_png, service_png):
        data = encode(frame)
        assert np.array_equal(_pillow(data), frame)  # lossless, a PNG any decoder reads
        assert len(data) <= 1.05 * len(_png(frame, compress_level=1))
    assert np.array_equal(_pillow(service_png(grey)), grey)  # feature previews may be single-channel
