"""A frame's msgpack body as the SDK sends it, and what is done to a frame before it goes: depth in
16-bit sensor units where that is lossless, colour as PNG, colour brought to the pixels of depth
registered at a lower resolution, a frame without depth downscaled to the service's limit, a class
map as its ids. Also PNG bytes back to numpy."""

from __future__ import annotations

import io
import math
import numbers
import os
import warnings
from typing import Literal, get_args

import numpy as np

from canonical_wire import COLOUR_MODES, IMAGE_FORMATS, encode_array, pack

MSGPACK = "application/msgpack"
FrameCodec = Literal["compact", "raw"]
FRAME_CODECS = get_args(FrameCodec)


def wire_matrix(m, shape: tuple[int, int], name: str) -> list:
    """``m`` as the nested lists of floats a body carries (msgpack or JSON); ValueError naming the
    argument ``name`` unless it is numbers of shape ``shape``, before anything is sent. A pose (4x4)
    may be its top three rows, 3x4, as the service takes it.

    Example:
        >>> wire_matrix(np.eye(4), (3, 3), "K")
        Traceback (most recent call last):
        ValueError: K: expected a 3x3 matrix, got shape [4, 4]
    """
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a {shape[0]}x{shape[1]} matrix of numbers ({exc})") from None
    if a.shape != shape and not (shape == (4, 4) and a.shape == (3, 4)):
        raise ValueError(f"{name}: expected a {shape[0]}x{shape[1]} matrix, got shape {list(a.shape)}")
    return a.tolist()


def check_depth_scale(depth_scale) -> float:
    """``depth_scale`` (sensor units per metre) as a float; ValueError naming it when it is missing,
    not positive or not finite."""
    if isinstance(depth_scale, bool) or not isinstance(depth_scale, numbers.Real) or not depth_scale > 0 \
            or not math.isfinite(depth_scale):
        raise ValueError(f"depth_scale: integer depth needs its units per metre (e.g. 1000 for millimetres), got {depth_scale!r}")
    return float(depth_scale)


def sensor_depth(depth, depth_scale) -> np.ndarray:  # [H, W] integers -> [H, W] uint16
    """A sensor's integer depth as the 16-bit array it travels as; ValueError (naming the field) for a
    missing or non-positive ``depth_scale`` or values outside 0..65535."""
    check_depth_scale(depth_scale)
    depth = np.asarray(depth)
    if depth.size and (depth.min() < 0 or depth.max() > 65535):
        raise ValueError(f"depth: integer depth must fit 16 bits (0..65535), got values {depth.min()}..{depth.max()}")
    return depth.astype(np.uint16, copy=False)


def exact_sensor_depth(depth, scales=(1000.0, 5000.0, 10000.0, 4000.0)) -> tuple[np.ndarray, float] | None:
    """``depth`` (float metres, 0 = missing) as (16-bit sensor units, units per metre) when that is
    lossless: the service's conversion of those units gives back exactly these float32 metres (as
    with depth read from a 16-bit depth image). None when no scale of ``scales`` does.

    Example:
        >>> raw, scale = exact_sensor_depth(np.array([[0.0, 0.5]], np.float32))
        >>> raw.tolist(), scale
        ([[0, 500]], 1000.0)
    """
    metres = np.asarray(depth, dtype=np.float32)
    if metres.size == 0 or not np.isfinite(metres).all() or metres.min() < 0:
        return None
    for scale in scales:
        units = np.rint(metres.astype(np.float64) * scale)
        if units.max() >= 65535:  # 65535 is a missing-depth code on the service's side
            continue
        units = units.astype(np.uint16)
        if np.array_equal((units / scale).astype(np.float32), metres):
            return units, scale
    return None


def frame_body(rgb, K, c2w, depth=None, depth_std=None, features=None, labels=None, frame_id=None,
               depth_scale=None, num_classes=None, codec: FrameCodec = "compact") -> bytes:
    """The msgpack body of one frame as `Session.add_frame` sends it (its arguments, the same checks).

    ``codec`` "compact" (the default) sends what is lossless and small: an ``rgb`` array as a PNG
    (fast level), integer depth, and float depth that 16-bit sensor units hold exactly
    (`exact_sensor_depth`), as zstandard-compressed uint16 with its ``depth_scale``, other float depth
    as zstandard-compressed float32, and label scores zstandard-compressed; where depth is registered
    at a lower resolution than the colour (a phone's), the colour brought to the depth's pixels as a
    PNG (`fit_colour_to_depth`: the frame the service would make of the whole image). "raw" sends the
    arrays as they are. PNG/JPEG ``rgb`` bytes (but for that fit) and 16-bit PNG ``depth`` bytes (with
    ``depth_scale``) travel untouched. The service folds the same frame from all of them.

    ``labels`` as a class map (integer [H', W'], negative for none) travel as int16 ids with their
    ``num_classes`` (required with one), not one-hot: the service expands each pixel it folds.
    """
    if codec not in FRAME_CODECS:
        raise ValueError(f"codec: expected one of {list(FRAME_CODECS)}, got {codec!r}")
    for name, value in (("rgb", rgb), ("depth", depth)):
        if isinstance(value, (str, os.PathLike)):  # what a new user tries first: the file's bytes are what travel
            raise ValueError(f"{name}: expected an array or the image file's bytes, got the path {str(value)!r} "
                             "(pass pathlib.Path(...).read_bytes())")
    array_codec = "zstd" if codec == "compact" else "raw"
    if codec == "compact" and depth is not None:
        rgb, K = fit_colour_to_depth(rgb, K, depth)
    if isinstance(rgb, (bytes, bytearray)):
        rgb = bytes(rgb)
    elif codec == "compact" and np.asarray(rgb).dtype == np.uint8 and np.shape(rgb)[2:] == (3,):
        rgb = encode_png(np.asarray(rgb))  # not [H, W, 4] or [H, W, 1]: as an array the service refuses them, as "raw" does
    else:
        rgb = encode_array(rgb, "rgb")
    msg: dict = {"rgb": rgb, "K": wire_matrix(K, (3, 3), "K"), "c2w": wire_matrix(c2w, (4, 4), "c2w")}
    if depth is not None and depth_scale is None and codec == "compact" and np.issubdtype(np.asarray(depth).dtype, np.floating):
        depth, depth_scale = exact_sensor_depth(depth) or (depth, None)
    if isinstance(depth, (bytes, bytearray)):  # a 16-bit depth PNG, as a depth camera's files hold it
        msg["depth"], msg["depth_scale"] = bytes(depth), check_depth_scale(depth_scale)
        depth = None
    elif depth is not None and np.issubdtype(np.asarray(depth).dtype, np.integer):
        msg["depth"] = encode_array(sensor_depth(depth, depth_scale), "depth", array_codec)
        msg["depth_scale"] = float(depth_scale)
        depth = None
    elif depth_scale is not None:  # a float depth is in metres already: a scale would be applied twice or ignored
        raise ValueError("depth_scale: only with integer depth (sensor units); float depth is in metres")
    if depth is not None:
        msg["depth"] = encode_array(np.asarray(depth, np.float32), "depth", array_codec)
    if isinstance(labels, (bytes, bytearray)):  # a class map PNG (0 no class, k + 1 class k), as a file holds it
        if num_classes is None:
            raise ValueError("num_classes: required with a class map PNG (labels as PNG bytes)")
        msg["labels"], msg["num_classes"], labels = bytes(labels), int(num_classes), None
    elif labels is not None and is_class_map(labels):
        if num_classes is None:
            raise ValueError("num_classes: required with a class map (labels as integer [H', W'])")
        ids = np.asarray(labels)
        if ids.size and (ids.max() >= num_classes or ids.max() > np.iinfo(np.int16).max):
            raise ValueError(f"labels: class {int(ids.max())} does not fit K = {num_classes} label classes "
                             f"(ids 0..{num_classes - 1}); a session's K is fixed by its first labelled frame")
        msg["labels"] = encode_array(np.maximum(ids.astype(np.int64), -1).astype(np.int16), "labels", array_codec)
        msg["num_classes"], labels = int(num_classes), None
    elif num_classes is not None:
        raise ValueError("num_classes: goes with a class map (labels as integer [H', W']); label scores carry K "
                         "as their last axis")
    for name, value in (("depth_std", depth_std), ("features", features), ("labels", labels)):
        if value is not None:
            value = np.asarray(value)
            # float maps gain little from lossless compression and travel as they are, but label scores
            # are mostly a class map one-hot encoded: zstandard packs those a few hundred times smaller
            msg[name] = encode_array(value if value.dtype == np.float16 else value.astype(np.float32), name,
                                     array_codec if name == "labels" else "raw")
    if frame_id is not None:
        msg["frame_id"] = str(frame_id)
    return pack(msg)


# zlib's fastest level: a colour frame packs nearly as small as at the default level in a fraction
# of its time (the client's CPU is often the service's too)
PNG_LEVEL = 1


def encode_png(rgb: np.ndarray) -> bytes:  # [H, W, 3] uint8 -> PNG bytes
    """A colour image as a lossless PNG, encoded by libpng (imagecodecs) at a fast compression level
    (`PNG_LEVEL`) with zlib's run-length strategy and every row's filter "sub": on camera frames that
    packs as small as Pillow's fastest level in about a third of its time, and the service decodes it
    faster too."""
    import imagecodecs

    return imagecodecs.png_encode(np.ascontiguousarray(rgb, np.uint8), level=PNG_LEVEL,
                                  strategy=imagecodecs.PNG.STRATEGY.RLE, filter=imagecodecs.PNG.FILTER.SUB)


class DownscaledFrame(UserWarning):
    """A frame without depth was over the service's limit for such frames and was sent downscaled."""


def scaled_intrinsics(K, sx: float, sy: float) -> np.ndarray:  # [3, 3] float64
    """``K`` of the image resized by ``sx`` across and ``sy`` down. Pixel centres sit on integers (the
    convention of `canonical_core.camera`: pixel u spans u - 0.5 .. u + 0.5), so the image's edges
    stay its edges: c' + 0.5 = (c + 0.5) s, the rule of `Camera.resized` (`resized_intrinsics`).

    Example:
        >>> scaled_intrinsics([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], 0.5, 0.5)[:2].tolist()
        [[250.0, 0.0, 159.5], [0.0, 250.0, 119.5]]
    """
    from canonical_core.resample import resized_intrinsics  # numpy only (loaded when a frame is resized)

    return resized_intrinsics(np.array(wire_matrix(K, (3, 3), "K")), sx, sy)


def _image_size(image) -> tuple[int, int] | None:
    """(width, height) of an array or of image bytes (from their header); None for anything else."""
    if isinstance(image, (bytes, bytearray)):
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(io.BytesIO(bytes(image))) as opened:
                return opened.size
        except (UnidentifiedImageError, OSError):  # not an image: the service names the problem
            return None
    shape = np.shape(image)
    return (shape[1], shape[0]) if len(shape) in (2, 3) else None


def _colour_array(rgb) -> np.ndarray | None:
    """``rgb`` as an array: image bytes decoded to uint8 [H, W, 3] (Pillow, as the service decodes them),
    or None for bytes the service would refuse (another format, or not 8-bit colour): they are sent as
    they are, so that the service names the problem whatever the frame's depth."""
    if isinstance(rgb, (bytes, bytearray)):
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(io.BytesIO(bytes(rgb))) as image:
                if image.format not in IMAGE_FORMATS or image.mode not in COLOUR_MODES:
                    return None
                return np.asarray(image.convert("RGB"))
        except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
            return None
    return np.asarray(rgb)


def fit_colour_to_depth(rgb, K, depth) -> tuple[object, object]:
    """``(rgb, K)`` of a frame whose depth is registered at a lower resolution than its colour (a
    phone's LiDAR: 256x192 depth for a 1920x1440 image): the colour area-averaged to the depth's
    pixels and K resized to match, the frame the service makes of the whole image
    (`canonical_core.resample`, the same code: the same scene, bit for bit), sent in a fraction of
    its bytes. Colour given as PNG or JPEG bytes is decoded here first (Pillow, as the service
    decodes it). As they are otherwise: depth at the image's size, or of another shape (which the
    service refuses, naming it).

    Example:
        >>> rgb, K = fit_colour_to_depth(np.zeros((1440, 1920, 3), np.uint8), np.diag([1500.0, 1500.0, 1.0]),
        ...                              np.zeros((192, 256), np.float32))
        >>> rgb.shape, float(K[0, 0])
        ((192, 256, 3), 200.0)
    """
    image, size = _image_size(rgb), _image_size(depth)
    if image is None or size is None or size == image:
        return rgb, K
    # the service's own rule, loaded only here: numpy and Pillow, no torch (`import client.sdk` loads none of it)
    from canonical_core.resample import area_resize, depth_size_problem

    if depth_size_problem(image, size) is not None:
        return rgb, K
    colour = _colour_array(rgb)
    if colour is None or colour.dtype != np.uint8 or colour.ndim != 3 or colour.shape[2] != 3:  # the service says why
        return rgb, K
    return area_resize(colour, size), scaled_intrinsics(K, size[0] / image[0], size[1] / image[1])


def fit_rgb_only(rgb, K, max_pixels: int) -> tuple[object, object]:
    """``(rgb, K)`` of a frame without depth, fitted to ``max_pixels``: as they are when within it,
    else the image area-averaged down to the largest size within it (aspect kept) and K scaled to
    match (`scaled_intrinsics`), with a `DownscaledFrame` warning."""
    width, height = _image_size(rgb) or (0, 0)
    colour = None if width * height <= max_pixels else _colour_array(rgb)
    if colour is None or colour.ndim != 3:
        return rgb, K  # within the limit, or not an image the service takes (it names the problem)
    from canonical_core.resample import area_resize  # numpy and Pillow, no torch

    factor = math.sqrt(max_pixels / (width * height))
    size = (max(1, int(width * factor)), max(1, int(height * factor)))  # rounded down: within the limit
    warnings.warn(f"rgb: a frame without depth of {width}x{height} pixels is over the service's limit of {max_pixels} "
                  f"pixels for such frames; sent downscaled to {size[0]}x{size[1]}, with K scaled to match (or send "
                  f"depth)", DownscaledFrame, stacklevel=4)  # the caller of `Session.add_frame`
    return area_resize(colour, size), scaled_intrinsics(K, size[0] / width, size[1] / height)


def is_class_map(labels) -> bool:
    """Whether ``labels`` is a class map (integer or boolean [H, W]: one class id a pixel), not scores."""
    labels = np.asarray(labels)
    return labels.ndim == 2 and (np.issubdtype(labels.dtype, np.integer) or labels.dtype == np.bool_)


def png_to_array(data: bytes) -> np.ndarray:
    """PNG bytes -> numpy (uint8 [H,W,3] for colour, [H,W] for palette/grey)."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)))
