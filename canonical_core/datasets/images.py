"""Reading and writing the image files captures are made of: colour images and 16-bit depth maps
(PNG, TIFF, binary PGM), the PNGs that cameras write decoded by libpng.

Every reader raises ``ValueError`` naming the file and the problem, so a loader's error says which
file of a capture is missing or broken.

Example:
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> p = Path(tempfile.mkdtemp()) / "d.png"
    >>> write_depth(p, np.array([[0.0, 0.5]], np.float32), depth_scale=1000.0)
    >>> read_depth(p, depth_scale=1000.0).tolist()
    [[0.0, 0.5]]
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

# uint16 depth code for "no measurement" besides 0: 7-Scenes writes 65535 for invalid pixels, and no
# sensor at a mm (or TUM's 1/5000 m) scale measures 65.5 m (13.1 m), so it is never a real depth.
DEPTH_INVALID_CODE = 65535
_PGM_SUFFIXES = (".pgm", ".pnm")


# Pillow modes whose PNG pixels libpng decodes into exactly the array Pillow gives: (channels, dtype)
_LIBPNG_LAYOUTS = {"RGB": (3, np.uint8), "I;16": (0, np.uint16)}


def png_pixels(image: Image.Image, data: bytes) -> np.ndarray | None:  # [H, W, 3] uint8 or [H, W] uint16
    """The pixels of ``image``, opened from ``data`` with only its header read, decoded by libpng
    (imagecodecs) straight into a numpy array, for the two layouts cameras write: 8-bit RGB and
    16-bit grey PNG, not interlaced; None for every other image (Pillow decodes those). A file libpng
    refuses raises ValueError with libpng's reason: Pillow would take some such files, filling what
    is missing (rows a short data stream lacks) with black.

    Why not Pillow alone: a service decodes every frame it is sent, and Pillow decodes into its own
    buffer and copies it out, where libpng here writes the array once with faster row filters.
    The arrays are equal to Pillow's (tested on every capture).

    Example:
        >>> import io
        >>> buf = io.BytesIO(); Image.fromarray(np.zeros((2, 3, 3), np.uint8)).save(buf, format="PNG")
        >>> png_pixels(Image.open(buf), buf.getvalue()).shape
        (2, 3, 3)
    """
    layout = _LIBPNG_LAYOUTS.get(image.mode) if image.format == "PNG" else None
    if layout is None or image.info.get("interlace"):  # libpng warns on stderr for every interlaced one
        return None
    import imagecodecs  # loaded with the first decode: listing a capture or streaming its files needs none

    try:
        pixels = imagecodecs.png_decode(data)
    except Exception as exc:  # libpng's errors surface as several types (its message is not always text)
        raise ValueError(f"libpng: {str(exc)[:200] or type(exc).__name__}") from None
    channels, dtype = layout
    shape = (image.height, image.width, channels) if channels else (image.height, image.width)
    return pixels if pixels.shape == shape and pixels.dtype == dtype else None


def _open_image(path: Path, with_bytes: bool = False) -> tuple[Image.Image, bytes]:
    # the image with only its header read, and the file's bytes where asked for (else b"")
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    try:
        data = path.read_bytes() if with_bytes else b""
        return Image.open(io.BytesIO(data) if with_bytes else path), data
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise ValueError(f"{path}: unreadable image ({exc})") from None


def _pixels(path: Path, modes: tuple[str, ...], expected: str) -> tuple[Image.Image, np.ndarray | None]:
    # the image in one of ``modes``, and its pixels where libpng decoded them (else Pillow has loaded them)
    image, data = _open_image(path, with_bytes=True)
    if image.mode not in modes:
        raise ValueError(f"{path}: expected {expected}, got PIL mode {image.mode!r}")
    try:
        pixels = png_pixels(image, data)
        if pixels is None:
            image.load()
    except (OSError, SyntaxError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable image ({exc})") from None
    return image, pixels


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    with _open_image(Path(path))[0] as image:
        return image.size


def read_rgb(path: str | Path) -> np.ndarray:  # [H, W, 3] uint8
    """Read an 8-bit colour (or grey, palette, RGBA: alpha dropped) image as uint8 RGB [H, W, 3]."""
    image, pixels = _pixels(Path(path), ("RGB", "RGBA", "L", "LA", "P", "CMYK", "YCbCr"), "an 8-bit colour image")
    return pixels if pixels is not None else np.array(image.convert("RGB"))  # writable: torch warns on read-only arrays


def read_pgm(path: str | Path) -> np.ndarray:  # [H, W] uint16
    """Read a binary (P5) PGM as raw integers [H, W] uint16.

    Written here rather than left to Pillow: Pillow rescales samples to 0..65535 when the header's
    maxval is not 65535 (e.g. 4095), which would corrupt depth in millimetres. 16-bit samples are
    big-endian, as the Netpbm format defines.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    data = path.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < 4:  # magic, width, height, maxval; '#' comments may sit between them
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.find(b"\n", pos)
            if pos < 0:
                break
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            break
        tokens.append(data[start:pos])
    if len(tokens) < 4 or tokens[0] != b"P5":
        raise ValueError(f"{path}: not a binary PGM (expected header 'P5 width height maxval', got {tokens[:4]})")
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError:
        raise ValueError(f"{path}: malformed PGM header {tokens}") from None
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise ValueError(f"{path}: invalid PGM header: width={width}, height={height}, maxval={maxval}")
    pos += 1  # exactly one whitespace byte separates the header from the samples
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
    count = width * height
    if len(data) - pos < count * dtype.itemsize:
        raise ValueError(f"{path}: truncated PGM: {len(data) - pos} bytes of samples, expected {count * dtype.itemsize}")
    samples = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
    return samples.reshape(height, width).astype(np.uint16)


def read_depth(path: str | Path, depth_scale: float) -> np.ndarray:  # [H, W] float32 metres
    """Read a 16-bit depth image (PNG/TIFF, or binary PGM) as float32 metres: value / depth_scale.

    0 and 65535 (the 7-Scenes invalid code) become 0 = missing.

    Example:
        >>> d = read_depth("frame-000015.depth.png", depth_scale=1000.0)  # doctest: +SKIP
    """
    path = Path(path)
    check_depth_scale(depth_scale)
    if path.suffix.lower() in _PGM_SUFFIXES:
        raw = read_pgm(path)
    else:
        image, raw = _pixels(path, ("I;16", "I;16B", "I;16L", "I"), "a 16-bit single-channel depth image")
        if raw is None:
            raw = np.asarray(image)
        if raw.dtype != np.uint16:  # mode "I" is int32: accept it only when it holds 16-bit values
            if raw.size and (raw.min() < 0 or raw.max() > DEPTH_INVALID_CODE):
                raise ValueError(f"{path}: depth values {raw.min()}..{raw.max()} do not fit 16 bits")
            raw = raw.astype(np.uint16)
    return depth_from_uint16(raw, depth_scale)


DEPTH_SCALE_RANGE = (1e-3, 1e9)  # depth units per metre: from a unit of a kilometre to one of a nanometre


def check_depth_scale(value, field: str = "depth_scale") -> float:
    """``value`` (integer depth units per metre: a code / ``value`` = metres) as a float. ValueError
    naming ``field`` for what is not a number within `DEPTH_SCALE_RANGE`: a scale near 0 would put
    every code at an infinite depth.

    Example:
        >>> check_depth_scale(1000)
        1000.0
    """
    low, high = DEPTH_SCALE_RANGE
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not low <= value <= high:
        raise ValueError(f"{field}: expected depth units per metre between {low:g} and {high:g} (e.g. 1000 for "
                         f"millimetres), got {value!r}")
    return float(value)


def depth_from_uint16(raw: np.ndarray, depth_scale: float) -> np.ndarray:  # [H, W] uint16 -> float32 metres
    """Metres = value / depth_scale (divided in float64, then rounded to float32); 0 and 65535 (the
    7-Scenes invalid code) become 0 = missing. One pass: the service converts every 16-bit frame it
    is sent."""
    from .depth_codes import metres_kernel  # numba loads with the first conversion, not with the loaders

    raw = np.ascontiguousarray(raw, dtype=np.uint16)
    metres = np.empty(raw.shape, np.float32)
    metres_kernel(raw.reshape(-1), float(depth_scale), DEPTH_INVALID_CODE, metres.reshape(-1))
    return metres


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write uint8 [H, W, 3] as PNG (lossless, so a re-read equals the input)."""
    Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), mode="RGB").save(path, format="PNG")


def write_depth(path: str | Path, depth: np.ndarray, depth_scale: float) -> None:
    """Write float metres [H, W] as a uint16 PNG of round(depth * depth_scale); 0 = missing.

    Raises ValueError when a depth does not fit (>= 65535 / depth_scale metres) or is negative.
    """
    if not depth_scale > 0:
        raise ValueError(f"depth_scale: expected a positive number, got {depth_scale!r}")
    depth = np.asarray(depth, dtype=np.float64)
    depth = np.where(np.isfinite(depth), depth, 0.0)
    raw = np.round(depth * depth_scale)
    if raw.size and (raw.min() < 0 or raw.max() >= DEPTH_INVALID_CODE):
        raise ValueError(
            f"{path}: depth {depth.min():g}..{depth.max():g} m does not fit a uint16 PNG at depth_scale={depth_scale:g} "
            f"(valid 0..{(DEPTH_INVALID_CODE - 1) / depth_scale:g} m)"
        )
    Image.fromarray(raw.astype(np.uint16)).save(path, format="PNG")
