"""The wire format: msgpack arrays, PNG/JPEG images, 16-bit depth PNGs, and frame messages.

An array travels as ``{"dtype": "uint8"|"uint16"|"float16"|"float32", "shape": [...], "data": <bytes,
little-endian, C order>}``. A frame message is a msgpack map with ``rgb`` (array or PNG/JPEG bytes),
``K`` [3][3], ``c2w`` [4][4] and optional ``depth`` (float array in metres, or a uint16 array / 16-bit
PNG with ``depth_scale`` units per metre), ``depth_std``, ``features``, ``labels``, ``frame_id``,
``width``, ``height``.

Every problem raises `WireError` naming the field; nothing here knows about HTTP.
"""

from __future__ import annotations

import colorsys
import io
import math

import msgpack
import numpy as np
from PIL import Image, UnidentifiedImageError

from canonical_core import Camera, Frame
from canonical_core.datasets.files import DEPTH_INVALID_CODE, depth_from_uint16

DTYPES = {"uint8": np.dtype("<u1"), "uint16": np.dtype("<u2"), "float16": np.dtype("<f2"), "float32": np.dtype("<f4")}
FLOATS = ("float16", "float32")
IMAGE_FORMATS = ("PNG", "JPEG")
FRAME_FIELDS = ("rgb", "K", "c2w", "depth", "depth_scale", "depth_std", "features", "labels", "frame_id", "width", "height")
NO_LABEL = 65535  # uint16 label maps: pixels that nothing covers


class WireError(ValueError):
    """A request that cannot be decoded. ``status`` is the HTTP status it deserves (400, 413, 422)."""

    def __init__(self, field: str, message: str, status: int = 422, code: str = "invalid_value"):
        super().__init__(f"{field}: {message}")
        self.field, self.status, self.code = field, status, code


# -- msgpack ------------------------------------------------------------------------------------
def unpack(body: bytes) -> dict:
    """A msgpack map from ``body``; WireError(400) when it is not one."""
    try:
        obj = msgpack.unpackb(body, raw=False, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types for broken input
        raise WireError("body", f"malformed msgpack ({type(exc).__name__}: {exc})", 400, "malformed_body") from None
    if not isinstance(obj, dict):
        raise WireError("body", f"expected a msgpack map, got {type(obj).__name__}", 400, "malformed_body")
    return obj


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def encode_array(a: np.ndarray) -> dict:
    a = np.asarray(a)
    name = a.dtype.name
    if name not in DTYPES:
        raise ValueError(f"array: dtype {name} is not one of {list(DTYPES)}")
    return {"dtype": name, "shape": list(a.shape), "data": np.ascontiguousarray(a, DTYPES[name]).tobytes()}


def is_array(obj) -> bool:
    return isinstance(obj, dict) and set(obj) == {"dtype", "shape", "data"}


def decode_array(obj, field: str, dtypes=tuple(DTYPES), ndim: int | None = None) -> np.ndarray:
    """An owned, native-order numpy array from an array map; WireError(422) naming ``field``."""
    if not is_array(obj):
        got = sorted(obj) if isinstance(obj, dict) else type(obj).__name__
        raise WireError(field, f"expected an array map {{dtype, shape, data}}, got {got}")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if dtype not in dtypes:
        raise WireError(field, f"dtype {dtype!r} is not accepted here; expected one of {list(dtypes)}")
    if not isinstance(shape, (list, tuple)) or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape):
        raise WireError(field, f"shape must be a list of non-negative integers, got {shape!r}")
    if ndim is not None and len(shape) != ndim:
        raise WireError(field, f"expected {ndim} dimensions, got shape {list(shape)}")
    if not isinstance(data, (bytes, bytearray)):
        raise WireError(field, f"data must be bytes, got {type(data).__name__}")
    expected = math.prod(shape) * DTYPES[dtype].itemsize
    if len(data) != expected:
        raise WireError(field, f"data holds {len(data)} bytes; shape {list(shape)} of {dtype} needs {expected}")
    return np.frombuffer(data, DTYPES[dtype]).reshape(shape).astype(DTYPES[dtype].newbyteorder("="), copy=True)


# -- images -------------------------------------------------------------------------------------
def _open_image(data: bytes, field: str, max_pixels: int | None) -> Image.Image:
    try:
        image = Image.open(io.BytesIO(data))
    except (UnidentifiedImageError, OSError, ValueError):
        raise WireError(field, f"not a PNG or JPEG image ({len(data)} bytes starting {data[:8]!r})") from None
    if image.format not in IMAGE_FORMATS:
        raise WireError(field, f"image format {image.format} is not accepted; send PNG or JPEG")
    check_pixels(image.width, image.height, field, max_pixels)  # before decoding the pixels
    try:
        image.load()
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise WireError(field, f"corrupt {image.format} image ({exc})") from None
    return image


def check_pixels(width: int, height: int, field: str, max_pixels: int | None) -> None:
    if max_pixels is not None and width * height > max_pixels:
        raise WireError(field, f"{width}x{height} = {width * height} pixels exceeds the limit of {max_pixels}", 413, "too_large")


def decode_rgb(data: bytes, field: str = "rgb", max_pixels: int | None = None) -> np.ndarray:  # [H, W, 3] uint8
    image = _open_image(data, field, max_pixels)
    if image.mode not in ("RGB", "RGBA", "L", "LA", "P", "CMYK", "YCbCr"):
        raise WireError(field, f"expected an 8-bit colour image, got PIL mode {image.mode!r}")
    return np.array(image.convert("RGB"))


def decode_depth_png(data: bytes, depth_scale, field: str = "depth", max_pixels: int | None = None) -> np.ndarray:
    """A 16-bit depth PNG -> float32 metres (value / depth_scale; 0 and 65535 = missing)."""
    image = _open_image(data, field, max_pixels)
    if image.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise WireError(field, f"expected a 16-bit single-channel depth PNG, got PIL mode {image.mode!r}")
    raw = np.asarray(image)
    if raw.dtype != np.uint16:
        if raw.size and (raw.min() < 0 or raw.max() > DEPTH_INVALID_CODE):
            raise WireError(field, "depth values do not fit 16 bits")
        raw = raw.astype(np.uint16)
    return depth_from_uint16(raw, depth_scale)


def encode_png(image: np.ndarray, compress_level: int = 3) -> bytes:
    """uint8 [H, W, 3] (or [H, W]) -> PNG bytes."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, np.uint8)).save(buf, format="PNG", compress_level=compress_level)
    return buf.getvalue()


def to_uint8(rgb01: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgb01, np.float32) * 255.0), 0, 255).astype(np.uint8)


def _palette() -> list[int]:
    # index 0 = no label (black); index k + 1 = label k: hues spaced by the golden ratio, fixed forever
    colours = [(0, 0, 0)]
    for k in range(255):
        r, g, b = colorsys.hsv_to_rgb((k * 0.618033988749895) % 1.0, 0.65 + 0.35 * (k % 2), 0.95 - 0.25 * ((k // 2) % 2))
        colours.append((round(r * 255), round(g * 255), round(b * 255)))
    return [c for rgb in colours for c in rgb]


LABEL_PALETTE = _palette()  # 256 RGB triples, flattened as PIL wants them


def encode_label_png(labels: np.ndarray) -> bytes:
    """int [H, W] labels (-1 = none, 0..254) -> palette PNG: index 0 none, index k + 1 label k."""
    if labels.size and labels.max() > 254:
        raise WireError("Accept", f"label {int(labels.max())} does not fit a palette PNG (0..254); ask for application/msgpack")
    image = Image.fromarray((labels + 1).astype(np.uint8), mode="P")
    image.putpalette(LABEL_PALETTE)
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    return buf.getvalue()


def labels_to_uint16(labels: np.ndarray) -> np.ndarray:
    """int [H, W] labels (-1 = none) -> uint16 with NO_LABEL (65535) for none."""
    return np.where(labels < 0, NO_LABEL, labels).astype(np.uint16)


# -- frames -------------------------------------------------------------------------------------
def _positive_number(value, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise WireError(field, f"expected a positive finite number, got {value!r}")
    return float(value)


def _matrix(value, field: str):
    return decode_array(value, field, FLOATS) if isinstance(value, dict) else value


def frame_from_message(msg: dict, max_pixels: int | None = None) -> Frame:
    """Decode and validate one frame message. Raises WireError (decoding) or ValueError (the library's
    validation, message starting with the field name)."""
    unknown = sorted(str(k) for k in msg if k not in FRAME_FIELDS)
    if unknown:
        raise WireError(unknown[0], f"unknown frame field (known: {list(FRAME_FIELDS)})")
    for name in ("rgb", "K", "c2w"):
        if msg.get(name) is None:
            raise WireError(name, "required field is missing")
    rgb = msg["rgb"]
    if isinstance(rgb, (bytes, bytearray)):
        rgb = decode_rgb(bytes(rgb), "rgb", max_pixels)
    else:
        if is_array(rgb) and isinstance(rgb["shape"], list) and len(rgb["shape"]) == 3 and all(isinstance(s, int) for s in rgb["shape"]):
            check_pixels(rgb["shape"][1], rgb["shape"][0], "rgb", max_pixels)
        rgb = decode_array(rgb, "rgb", ("uint8",), ndim=3)
    height, width = rgb.shape[:2]
    depth, scale = msg.get("depth"), msg.get("depth_scale")
    if scale is not None:
        scale = _positive_number(scale, "depth_scale")
    if isinstance(depth, (bytes, bytearray)):
        if scale is None:
            raise WireError("depth_scale", "required with a depth PNG (units per metre, e.g. 1000 for millimetres)")
        depth = decode_depth_png(bytes(depth), scale, "depth", max_pixels)
    elif depth is not None:
        depth = decode_array(depth, "depth", ("uint16", *FLOATS), ndim=2)
        if depth.dtype == np.uint16:
            if scale is None:
                raise WireError("depth_scale", "required with uint16 depth (units per metre, e.g. 1000 for millimetres)")
            depth = depth_from_uint16(depth, scale)
    elif scale is not None:
        raise WireError("depth_scale", "given without depth")
    extras = {}
    for name in ("depth_std", "features", "labels"):
        if msg.get(name) is not None:
            value = msg[name]
            if is_array(value) and isinstance(value["shape"], list) and len(value["shape"]) >= 2 and all(isinstance(s, int) for s in value["shape"]):
                check_pixels(value["shape"][1], value["shape"][0], name, max_pixels)
            extras[name] = decode_array(value, name, FLOATS, ndim=2 if name == "depth_std" else 3)
    size = (msg.get("width", width), msg.get("height", height))
    camera = Camera(_matrix(msg["K"], "K"), _matrix(msg["c2w"], "c2w"), *size)
    frame = Frame(rgb=rgb, camera=camera, depth=depth, frame_id=msg.get("frame_id"), **extras)
    _check_principal_point(camera)
    return frame


def _check_principal_point(camera: Camera) -> None:
    # A principal point outside the image means K belongs to another image size (e.g. full-res K
    # with a downscaled image): the library would fuse it silently into the wrong place.
    w, h = camera.width, camera.height
    if not (-0.5 <= camera.cx <= w - 0.5 and -0.5 <= camera.cy <= h - 0.5):
        raise WireError("K", f"principal point ({camera.cx:g}, {camera.cy:g}) lies outside the {w}x{h} image; is K for another image size?")
