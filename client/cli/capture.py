"""A capture's frames as keyword arguments of `Session.add_frame`: its files' own bytes where they can
travel as they are, else the decoded frame (optionally resized)."""

from __future__ import annotations

from typing import Iterator

import numpy as np

from ..sdk import exact_sensor_depth
from .common import UsageError, warnings_on_stderr


def load_capture(path, args, **options):
    """`load_dataset` of ``path`` with the command's ``--K`` and ``--depth-scale`` (and ``options``), its
    warnings on stderr. A capture without intrinsics, or an option its layout does not take, is a usage
    error naming the option; the capture's own problems stay ValueErrors (the command exits 1)."""
    from canonical_core.datasets import MissingIntrinsics, load_dataset

    try:
        with warnings_on_stderr():
            return load_dataset(path, K=args.K, depth_scale=args.depth_scale, **options)
    except MissingIntrinsics as exc:
        raise UsageError(f"--K: {exc} (here: --K fx,fy,cx,cy)") from None
    except ValueError as exc:
        for field, option in (("K: ", "--K"), ("depth_scale: ", "--depth-scale")):
            if str(exc).startswith(field):
                raise UsageError(f"{option}: {str(exc).removeprefix(field)}") from None
        raise


def frame_arrays(frame, scale: float = 1.0, sensor_units: bool = False) -> dict:
    """A canonical_core Frame -> keyword arguments of `Session.add_frame` (numpy), optionally resized:
    the colour bilinear, depth and its ``depth_std`` nearest (averaging depth across edges invents
    surfaces). Client features and labels travel at their own resolution whatever the scale: a frame
    takes them at any [H', W'] and looks them up nearest at its pixels, so class ids stay ids.

    With ``sensor_units``, depth that 16-bit sensor units hold exactly (depth read from a 16-bit depth
    image) travels as those units and their ``depth_scale``: half the depth's bytes, and the service
    folds the same float32 metres."""
    camera = frame.camera
    rgb = frame.rgb.numpy()
    depth, depth_std = (None if t is None else t.numpy() for t in (frame.depth, frame.depth_std))
    if scale != 1.0:
        from PIL import Image

        camera = camera.scaled(scale)
        size = (camera.width, camera.height)
        rgb = np.array(Image.fromarray(rgb).resize(size, Image.BILINEAR))
        depth, depth_std = (None if m is None else np.array(Image.fromarray(np.ascontiguousarray(m, np.float32))
                                                             .resize(size, Image.NEAREST)) for m in (depth, depth_std))
    out = {"rgb": rgb, "K": camera.K64(), "c2w": camera.c2w64(), "depth": depth, "frame_id": frame.frame_id}
    sensor = exact_sensor_depth(depth) if sensor_units and depth is not None else None
    if sensor is not None:
        out["depth"], out["depth_scale"] = sensor
    for name, value in (("depth_std", depth_std), ("features", frame.features), ("labels", frame.labels)):
        if value is not None:
            out[name] = value if isinstance(value, np.ndarray) else value.numpy()
    if frame.num_classes is not None:  # labels as a class map
        out["num_classes"] = frame.num_classes
    return out


def frame_files(source) -> dict | None:
    """A capture's frame (a `FrameSequence.source`) as keyword arguments of `Session.add_frame` that
    carry its files' own bytes: PNG or JPEG colour, 16-bit PNG depth with its ``depth_scale``. Nothing
    is decoded and encoded again (the client's CPU is often the service's), the capture's own
    compression is what travels and what the service keeps, and the service decodes the very frame
    the loader reads. None where the loader changes the images it reads (undistortion, depth that is
    not a PNG): send `frame_arrays` then. Where the depth is smaller than the
    colour (a phone's LiDAR beside its camera's image), the SDK sends the colour brought to the
    depth's pixels (`client.sdk.fit_colour_to_depth`), as the service would make it: a fraction of
    the whole image's bytes to send, decode and keep."""
    from canonical_core.datasets.files import IMAGE_SUFFIXES, RGBDFile

    if not isinstance(source, RGBDFile) or source.distortion is not None:
        return None
    if source.color.suffix.lower() not in IMAGE_SUFFIXES or (source.depth is not None and source.depth.suffix.lower() != ".png"):
        return None
    source.view()  # the image's size from its header against the capture's (ValueError naming the file)
    out = {"rgb": source.color.read_bytes(), "K": source.K, "c2w": source.c2w, "frame_id": source.frame_id}
    if source.depth is not None:
        out["depth"], out["depth_scale"] = source.depth.read_bytes(), source.depth_scale
    return out


def capture_frames(frames, scale: float = 1.0, start: int = 0) -> Iterator[dict]:
    """Frames ``start`` .. end of a capture as `Session.add_frame` keyword arguments, read one at a
    time: its files as they are (`frame_files`) where they can be, else decoded (`frame_arrays`,
    depth in its 16-bit sensor units)."""
    for i in range(start, len(frames)):
        files = frame_files(frames.source(i)) if scale == 1.0 else None
        yield files if files is not None else frame_arrays(frames[i], scale, sensor_units=True)
