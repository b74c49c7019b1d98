"""An image brought to another resolution: its colour area-averaged, and the intrinsics that go with it.

A frame whose depth is registered at a lower resolution than its colour (phone LiDAR, time-of-flight
cameras) is folded at the depth's pixels, its colour averaged over each depth pixel's footprint
(`canonical_core.frame.Frame`). The SDK applies the same rule before it sends such a frame, so that a
1920x1440 image for 256x192 depth travels as the 256x192 image the service would have made of it, a
fiftieth of its pixels. Both ends use this module, so both give the same frame, bit for bit.
numpy and Pillow only: the SDK loads it, when it fits a frame, without torch.
"""

from __future__ import annotations

import numpy as np
from PIL import Image


def area_resize(
    rgb: np.ndarray,  # [H, W, 3] uint8
    size: tuple[int, int],  # (width, height) of the result
) -> np.ndarray:  # [height, width, 3] uint8
    """Colour area-averaged to ``size``. Where ``size`` divides the image's sides by whole factors
    (half size: the colour solve's kept views), each output pixel is the mean of its block
    (`Image.reduce`), rounded exactly for power-of-two blocks; Pillow's box filter, used otherwise,
    weighs in fixed point, and at half size it is off by one in about a third of the values and
    takes four times as long.

    Example:
        >>> area_resize(np.array([[[0, 0, 0], [1, 2, 255]], [[2, 2, 0], [2, 3, 255]]], np.uint8), (1, 1))
        array([[[  1,   2, 128]]], dtype=uint8)
    """
    height, width = rgb.shape[:2]
    image = Image.fromarray(np.ascontiguousarray(rgb, np.uint8))
    if width % size[0] == 0 and height % size[1] == 0:
        return np.array(image.reduce((width // size[0], height // size[1])))
    return np.array(image.resize(size, Image.BOX))


def resized_intrinsics(
    K: np.ndarray,  # [3, 3] float64 pinhole matrix, no skew
    sx: float,  # new width / old width
    sy: float,  # new height / old height
) -> np.ndarray:  # [3, 3] float64
    """``K`` of the image resized by ``sx`` across and ``sy`` down. Pixel centres sit on integers
    (pixel u spans u - 0.5 .. u + 0.5), so the image's edges stay its edges: c' + 0.5 = (c + 0.5) s.

    Example:
        >>> resized_intrinsics(np.array([[500.0, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]), 0.4, 0.4)[:2].tolist()
        [[200.0, 0.0, 127.5], [0.0, 200.0, 95.5]]
    """
    K = np.array(K, np.float64)
    K[0, 0] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


def transposed_map_problem(
    field: str,
    image: tuple[int, int],  # (width, height) of the image
    size: tuple[int, int],  # (width, height) of a client's feature or label map
) -> str | None:
    """Why a map of ``size`` looks transposed ([W', H'] sent as [H', W']): it has the image's shape
    turned a quarter (within a pixel) and not the image's own; else None. A map of any other size
    spans the image whatever its shape (a network's square output stretched back is meant so).

    Example:
        >>> transposed_map_problem("labels", (640, 480), (120, 160)) is not None
        True
        >>> transposed_map_problem("labels", (640, 480), (512, 512)) is None
        True
    """
    (W, H), (w, h) = image, size
    tolerance = max(W, H, w, h)
    if abs(h * H - w * W) <= tolerance and abs(w * H - h * W) > tolerance:
        return (f"{field}: a {w}x{h} map has the {W}x{H} image's shape turned a quarter: an array [W', H'] "
                "where [H', W'] is meant? (transpose it)")
    return None


def depth_size_problem(
    image: tuple[int, int],  # (width, height) of the colour image
    depth: tuple[int, int],  # (width, height) of the depth map
) -> str | None:
    """Why depth of size ``depth`` cannot go with the image (larger than it, or of another shape:
    another camera's depth), or None when it can: at the image's size, or registered to it at a lower
    resolution, the image's sides any multiple of the depth's within a pixel (1920x1440 for 256x192).

    Example:
        >>> depth_size_problem((1920, 1440), (256, 192)) is None
        True
        >>> depth_size_problem((640, 480), (1280, 960))
        "depth: 1280x960 is larger than the rgb image 640x480; send depth at the image's resolution or lower, registered to the colour camera"
    """
    (W, H), (w, h) = image, depth
    if (w, h) == (W, H):
        return None
    if h > H or w > W:
        return (f"depth: {w}x{h} is larger than the rgb image {W}x{H}; send depth at the image's resolution "
                "or lower, registered to the colour camera")
    if h == H or w == W or abs(w * H - h * W) > max(H, W):  # not the image resampled (within a pixel): another view
        return (f"depth: {w}x{h} does not have the shape of the rgb image {W}x{H}; depth at another "
                "resolution must cover the image's field of view (registered to the colour camera)")
    return None
