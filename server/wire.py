"""The wire format: msgpack arrays, PNG/JPEG images, 16-bit depth PNGs, and frame messages.

Arrays travel in the codec of `canonical_wire` (re-exported here), the one the SDK uses. A frame
message is a msgpack map with ``rgb`` (array or PNG/JPEG bytes), ``K`` [3][3], ``c2w`` [4][4] and
optional ``depth`` (float array in metres, or a uint16 array / 16-bit
PNG with ``depth_scale`` units per metre), ``depth_std``, ``features``, ``labels`` (float scores
[H', W', K], or a class map with ``num_classes`` K: integer [H', W'] ids, negative for none, or a
PNG, 0 for none and k + 1 for class k),
``frame_id``, ``width``, ``height``.

Every problem raises `WireError` naming the field; nothing here knows about HTTP.
"""

from __future__ import annotations

import colorsys
import io
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from canonical_core import Camera, Frame
from canonical_core.datasets.images import DEPTH_INVALID_CODE, check_depth_scale, depth_from_uint16, png_pixels
from canonical_core.frame import check_rgb_only
from canonical_core.resample import transposed_map_problem
from canonical_wire import (COLOUR_MODES, DTYPES, FLOATS, IMAGE_FORMATS, INTEGERS, NO_LABEL, WireError,  # noqa: F401
                            array_shape, decode_array, encode_array, is_array, pack, unpack)

FRAME_FIELDS = ("rgb", "K", "c2w", "depth", "depth_scale", "depth_std", "features", "labels", "num_classes", "frame_id",
                "width", "height")


# -- images -------------------------------------------------------------------------------------
def _open_image(data: bytes, field: str, max_pixels: int | None, modes: tuple[str, ...], expected: str,
                expected_png: bool = False) -> tuple[Image.Image, np.ndarray | None]:
    """The image in one of ``modes`` (with ``expected_png``, a PNG's only), and its pixels where libpng
    decoded them (`png_pixels`; else Pillow has loaded them)."""
    # Image.open reads only the header; the size is checked before a pixel is decoded, so a small
    # file that decodes to gigapixels (a decompression bomb) costs nothing. Pillow refuses the
    # largest ones already in open().
    try:
        image = Image.open(io.BytesIO(data))
    except Image.DecompressionBombError as exc:
        raise WireError(field, f"image too large ({exc})", 413, "too_large") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        raise WireError(field, f"not a PNG or JPEG image ({len(data)} bytes starting {data[:8]!r})") from None
    if image.format not in IMAGE_FORMATS or (image.format != "PNG" and expected_png):
        raise WireError(field, f"image format {image.format} is not accepted; send {'a PNG' if expected_png else 'PNG or JPEG'}")
    check_pixels(image.width, image.height, field, max_pixels)  # before decoding the pixels
    if image.mode not in modes:
        raise WireError(field, f"expected {expected}, got PIL mode {image.mode!r}")
    try:
        pixels = png_pixels(image, data)
        if pixels is None:
            image.load()
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise WireError(field, f"corrupt {image.format} image ({exc})") from None
    return image, pixels


def check_pixels(width: int, height: int, field: str, max_pixels: int | None) -> None:
    if max_pixels is not None and width * height > max_pixels:
        raise WireError(field, f"{width}x{height} = {width * height} pixels exceeds the limit of {max_pixels}", 413, "too_large")


def decode_rgb(data: bytes, field: str = "rgb", max_pixels: int | None = None) -> np.ndarray:  # [H, W, 3] uint8
    image, pixels = _open_image(data, field, max_pixels, COLOUR_MODES, "an 8-bit colour image")
    if pixels is not None:
        return pixels
    # asarray reads the pixels out once (read-only; `Frame` copies such an array into its tensor), where
    # np.array goes through the image's array interface and copies them again, about ten times slower
    return np.asarray(image if image.mode == "RGB" else image.convert("RGB"))


def decode_depth_png(data: bytes, depth_scale, field: str = "depth", max_pixels: int | None = None) -> np.ndarray:
    """A 16-bit depth PNG -> float32 metres (value / depth_scale; 0 and 65535 = missing)."""
    image, raw = _open_image(data, field, max_pixels, ("I;16", "I;16B", "I;16L", "I"),
                             "a 16-bit single-channel depth PNG", expected_png=True)
    if raw is None:
        raw = np.asarray(image)
    if raw.dtype != np.uint16:
        if raw.size and (raw.min() < 0 or raw.max() > DEPTH_INVALID_CODE):
            raise WireError(field, "depth values do not fit 16 bits")
        raw = raw.astype(np.uint16)
    return depth_from_uint16(raw, depth_scale)


def decode_class_png(data: bytes, field: str = "labels", max_pixels: int | None = None) -> np.ndarray:  # [H, W] int32
    """A class map as an 8- or 16-bit single-channel PNG (grey or palette indices) -> class ids: value
    0 no class (-1), k + 1 class k, the layout of the service's own label PNGs (and ScanNet's label
    images). JPEG is refused: its compression changes ids at every edge."""
    expected = "an 8- or 16-bit single-channel class map PNG (0 no class, k + 1 class k)"
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) > 25 and data[24] < 8 \
            and data[25] == 0:  # grey of 1, 2 or 4 bits: Pillow scales its samples to 8 bits, which changes ids
        raise WireError(field, f"expected {expected}, got a {data[24]}-bit grey PNG")
    image, pixels = _open_image(data, field, max_pixels, ("L", "P", "I;16", "I;16B", "I;16L", "I"), expected)
    if image.format != "PNG":
        raise WireError(field, f"a class map travels as PNG, got {image.format}: lossy compression changes class ids")
    return (pixels if pixels is not None else np.asarray(image)).astype(np.int32) - 1


def encode_png(image: np.ndarray) -> bytes:  # uint8 [H, W, 3] or [H, W] -> PNG bytes
    """A rendered picture as PNG, encoded by libpng (imagecodecs): zlib's run-length strategy at its
    fastest level, row filters chosen per row. On renders this is about twice as fast as Pillow's
    default level, and a little smaller: a render's answer waits for it."""
    import imagecodecs

    return imagecodecs.png_encode(np.ascontiguousarray(image, np.uint8), level=1, strategy=imagecodecs.PNG.STRATEGY.RLE)


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
@dataclass(frozen=True)
class FrameLimits:
    """What one frame message may cost; None = only the library's own bounds.

    ``max_pixels``: image pixels (rgb, depth, and the feature/label maps' H' x W');
    ``max_rgb_only_pixels``: image pixels of a frame without depth (it is plane-swept and kept whole);
    ``max_label_channels``: label score channels, a class map's ``num_classes`` (each is a float per voxel
    for the session's life);
    ``max_channel_values``: image pixels x channels of ``features`` and of ``labels`` (both are
    sampled at every image pixel).
    """

    max_pixels: int | None = None
    max_rgb_only_pixels: int | None = None
    max_label_channels: int | None = None
    max_channel_values: int | None = None


MATRIX_SHAPES = {"K": ([3, 3],), "c2w": ([4, 4], [3, 4])}


def _matrix(value, field: str):
    if isinstance(value, dict):
        shape = array_shape(value)  # checked before its bytes are read: a small body may declare gigabytes
        if shape is not None and shape not in MATRIX_SHAPES[field]:
            raise WireError(field, f"expected shape {' or '.join(map(str, MATRIX_SHAPES[field]))}, got {shape}")
        return decode_array(value, field, FLOATS)
    if not _is_number_matrix(value):
        raise WireError(field, f"expected a matrix of numbers (a list of rows), got {str(value)[:80]!r}")
    return value


def _is_number_matrix(value) -> bool:
    # strict: no strings or booleans coerced to numbers
    return isinstance(value, list) and all(
        isinstance(row, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in row) for row in value)


def _size(value, field: str, default: int) -> int:
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int):
        raise WireError(field, f"expected an integer, got {value!r}")
    return value


def _check_channels(name: str, shape: list[int] | None, image_pixels: int, limits: FrameLimits) -> None:
    if shape is None or len(shape) != 3:
        return  # decode_array names the problem
    check_pixels(shape[1], shape[0], name, limits.max_pixels)
    if name == "labels":
        _check_label_channels(shape[2], name, limits)
    _check_channel_values(name, shape[2], image_pixels, limits)


def _check_label_channels(channels: int, field: str, limits: FrameLimits) -> None:
    if limits.max_label_channels is not None and channels > limits.max_label_channels:
        raise WireError(field, f"{channels} label channels exceed the limit of {limits.max_label_channels}", 413, "too_large")


def _check_channel_values(name: str, channels: int, image_pixels: int, limits: FrameLimits) -> None:
    """A map is sampled at every image pixel: pixels x channels values a frame, bounded."""
    if limits.max_channel_values is not None and image_pixels * channels > limits.max_channel_values:
        raise WireError(name, f"{channels} channels x {image_pixels} image pixels = {image_pixels * channels} values exceed "
                              f"the limit of {limits.max_channel_values}", 413, "too_large")


def _class_map(msg: dict, image_pixels: int, limits: FrameLimits) -> tuple[np.ndarray, int]:
    """``labels`` as a class map (an integer [H', W'] array, or PNG bytes: `decode_class_png`) with its
    ``num_classes``, the sizes checked before decoding. Fused as one-hot scores, so its K counts as
    that many label channels."""
    num_classes = msg.get("num_classes")
    if num_classes is None:
        raise WireError("num_classes", "required with a class map (labels as integer [H', W'] or a PNG): the number "
                                       "of classes K")
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise WireError("num_classes", f"expected a positive integer, got {num_classes!r}")
    _check_label_channels(num_classes, "num_classes", limits)
    _check_channel_values("labels", num_classes, image_pixels, limits)
    labels = msg["labels"]
    if isinstance(labels, (bytes, bytearray)):  # its size is checked from its header
        ids = decode_class_png(bytes(labels), "labels", limits.max_pixels)
        if ids.size and ids.max() >= num_classes:  # said in the PNG's values, which the sender wrote
            raise WireError("labels", f"PNG value {int(ids.max()) + 1} (class {int(ids.max())}) does not fit "
                                      f"num_classes = {num_classes} (values 0 = no class, 1..{num_classes})")
        return ids, num_classes
    shape = array_shape(labels)
    check_pixels(shape[1], shape[0], "labels", limits.max_pixels)
    return decode_array(labels, "labels", INTEGERS, ndim=2), num_classes


def frame_from_message(msg: dict, max_pixels: int | None = None, limits: FrameLimits | None = None,
                       fresh: bool = False) -> Frame:
    """Decode and validate one frame message. Raises WireError (decoding, sizes over ``limits``) or
    ValueError (the library's validation, message starting with the field name). ``fresh``: a frame
    as a client sends it, not one logged before (those are folded as they were taken): a feature or
    label map that looks transposed is refused (`resample.transposed_map_problem`)."""
    limits = limits or FrameLimits(max_pixels=max_pixels)
    max_pixels = limits.max_pixels
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
        shape = array_shape(rgb)
        if shape is not None and (len(shape) != 3 or shape[2] != 3):  # before its bytes are read
            raise WireError("rgb", f"expected shape [H, W, 3], got {shape}")
        if shape is not None:
            check_pixels(shape[1], shape[0], "rgb", max_pixels)
        rgb = decode_array(rgb, "rgb", ("uint8",), ndim=3)
    height, width = rgb.shape[:2]
    depth, scale = msg.get("depth"), msg.get("depth_scale")
    if depth is None and limits.max_rgb_only_pixels is not None and width * height > limits.max_rgb_only_pixels:
        raise WireError("rgb", f"a frame without depth of {width}x{height} = {width * height} pixels exceeds the limit of "
                               f"{limits.max_rgb_only_pixels} for frames without depth; send depth or a smaller image",
                        413, "too_large")
    if scale is not None:
        scale = check_depth_scale(scale)
    if isinstance(depth, (bytes, bytearray)):
        if scale is None:
            raise WireError("depth_scale", "required with a depth PNG (units per metre, e.g. 1000 for millimetres)")
        depth = decode_depth_png(bytes(depth), scale, "depth", max_pixels)
    elif depth is not None:
        shape = array_shape(depth)
        if shape is not None and len(shape) == 2:
            check_pixels(shape[1], shape[0], "depth", max_pixels)
        depth = decode_array(depth, "depth", ("uint16", *FLOATS), ndim=2)
        if depth.dtype != np.uint16 and scale is not None:  # it would be ignored: the frame folded at the wrong depth
            raise WireError("depth_scale", f"goes with integer depth (uint16 sensor units or a depth PNG); {depth.dtype} "
                                           "depth is in metres: send it without depth_scale")
        if depth.dtype == np.uint16:
            if scale is None:
                raise WireError("depth_scale", "required with uint16 depth (units per metre, e.g. 1000 for millimetres)")
            depth = depth_from_uint16(depth, scale)
    elif scale is not None:
        raise WireError("depth_scale", "given without depth")
    extras = {}
    labels = msg.get("labels")
    if isinstance(labels, (bytes, bytearray)) or (is_array(labels) and len(array_shape(labels) or ()) == 2):
        extras["labels"], extras["num_classes"] = _class_map(msg, width * height, limits)
    elif msg.get("num_classes") is not None and (labels is None or is_array(labels)):  # else labels' own error first
        raise WireError("num_classes", "goes with a class map (labels as integer [H', W'] or a PNG); label scores "
                                       "carry K as their last axis")
    for name in ("depth_std", "features", "labels"):
        if msg.get(name) is not None and name not in extras:
            value = msg[name]
            if name == "depth_std":
                shape = array_shape(value)
                if shape is not None and len(shape) == 2:
                    check_pixels(shape[1], shape[0], name, max_pixels)
            else:
                _check_channels(name, array_shape(value), width * height, limits)
            extras[name] = decode_array(value, name, FLOATS, ndim=2 if name == "depth_std" else 3)
    for name in ("features", "labels") if fresh else ():
        if name in extras and (problem := transposed_map_problem(name, (width, height), extras[name].shape[1::-1])):
            raise WireError(name, problem.removeprefix(f"{name}: "))
    for name, size in (("width", width), ("height", height)):  # a check: K of another size would fold elsewhere
        if _size(msg.get(name), name, size) != size:
            raise WireError(name, f"{msg[name]} does not match the rgb image's {size} pixels ({width}x{height}); K "
                                  "is the colour image's (resize it with the image, or leave width and height out)")
    camera = Camera(_matrix(msg["K"], "K"), _matrix(msg["c2w"], "c2w"), width, height)
    frame = Frame(rgb=rgb, camera=camera, depth=depth, frame_id=msg.get("frame_id"), **extras)
    check_rgb_only(frame)
    return frame
