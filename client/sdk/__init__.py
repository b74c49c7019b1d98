"""Python SDK for the CanonicalGS Fusion service: numpy in, numpy out, HTTP only.

Example:
    >>> client = Client("http://127.0.0.1:8000")                       # doctest: +SKIP
    >>> session = client.create_session(voxel_size=0.008)               # doctest: +SKIP
    >>> session.add_frame(rgb, K, c2w, depth=depth)["new_voxels"]       # doctest: +SKIP
    >>> view = session.render(K, c2w, 640, 480)                         # doctest: +SKIP
    >>> view["rgb"].shape, view["depth"].dtype                          # doctest: +SKIP
    ((480, 640, 3), dtype('float32'))

Every public name is importable from ``client.sdk`` itself; the modules split the work: `client`
(the connection, `Client`), `session` (`Session`), `frames` (a frame's body and what is done to a
frame before it goes), `stream` (frames with several in flight), `errors` (`CanonicalError`,
`ServiceUnreachable`, `StreamStopped`, `StreamRefused`).
"""

from canonical_wire import decode_array, encode_array, pack, unpack  # the codec the service uses too

from .client import Client, default_url
from .errors import CanonicalError, ServiceUnreachable, StreamRefused, StreamStopped
from .frames import (FRAME_CODECS, MSGPACK, PNG_LEVEL, DownscaledFrame, FrameCodec, check_depth_scale, encode_png,
                     exact_sensor_depth, fit_colour_to_depth, fit_rgb_only, frame_body, is_class_map, png_to_array,
                     scaled_intrinsics, sensor_depth)
from .session import Session

__all__ = ["CanonicalError", "Client", "DownscaledFrame", "FRAME_CODECS", "FrameCodec", "MSGPACK", "PNG_LEVEL", "ServiceUnreachable",
           "Session", "StreamRefused", "StreamStopped", "check_depth_scale", "decode_array", "default_url", "encode_array", "encode_png",
           "exact_sensor_depth", "fit_colour_to_depth", "fit_rgb_only", "frame_body", "is_class_map", "pack",
           "png_to_array", "scaled_intrinsics", "sensor_depth", "unpack"]
