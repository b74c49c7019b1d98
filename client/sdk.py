"""Python SDK for the CanonicalGS Fusion service: numpy in, numpy out, HTTP only.

Example:
    >>> client = Client("http://127.0.0.1:8000")                       # doctest: +SKIP
    >>> session = client.create_session(voxel_size=0.008)               # doctest: +SKIP
    >>> session.add_frame(rgb, K, c2w, depth=depth)["new_voxels"]       # doctest: +SKIP
    >>> view = session.render(K, c2w, 640, 480)                         # doctest: +SKIP
    >>> view["rgb"].shape, view["depth"].dtype                          # doctest: +SKIP
    ((480, 640, 3), dtype('float32'))
"""

from __future__ import annotations

import collections
import io
import itertools
import math
import numbers
import os
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterable, Iterator, Literal, get_args
from urllib.parse import quote

import httpx
import numpy as np

from canonical_wire import decode_array, encode_array, pack, unpack  # the codec the service uses too

MSGPACK = "application/msgpack"
FrameCodec = Literal["compact", "raw"]
FRAME_CODECS = get_args(FrameCodec)


class CanonicalError(Exception):
    """A 4xx/5xx answer: ``status``, ``code``, ``message`` and the offending ``field`` (or None)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.field = status, code, message, field


class StreamRefused(CanonicalError):
    """A frame of `Session.add_frames` was refused: its ``index`` in the session's stream, and how many
    frames of the call were ``acknowledged`` before it (folded, their reports yielded); the refusal's
    status, code, message and field as `CanonicalError`'s."""

    def __init__(self, refusal: CanonicalError, index: int, acknowledged: int):
        message = f"frame {index} refused (the session holds the {index} frames before it): {refusal.message}"
        super().__init__(refusal.status, refusal.code, message, refusal.field)
        self.index, self.acknowledged = index, acknowledged


def _matrix(m, shape: tuple[int, int]) -> list:
    a = np.asarray(m, dtype=np.float64)
    if a.shape != shape:
        raise ValueError(f"expected a {shape[0]}x{shape[1]} matrix, got shape {list(a.shape)}")
    return a.tolist()


def _view(K, c2w, width: int, height: int, max_gaussians: int | None, background, colour: str | None = None,
          depth: str | None = None) -> dict:
    body = {"K": _matrix(K, (3, 3)), "c2w": _matrix(c2w, (4, 4)), "width": int(width), "height": int(height)}
    if colour is not None:
        body["colour"] = colour
    if depth is not None:
        body["depth"] = depth
    if max_gaussians is not None:
        body["max_gaussians"] = int(max_gaussians)
    if background is not None:
        body["background"] = [float(x) for x in background]
    return body


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
               depth_scale=None, codec: FrameCodec = "compact") -> bytes:
    """The msgpack body of one frame as `Session.add_frame` sends it (its arguments, the same checks).

    ``codec`` "compact" (the default) sends what is lossless and small: an ``rgb`` array as a PNG
    (fast level), integer depth, and float depth that 16-bit sensor units hold exactly
    (`exact_sensor_depth`), as zstandard-compressed uint16 with its ``depth_scale``, other float depth
    as zstandard-compressed float32. "raw" sends the arrays as they are. PNG/JPEG ``rgb`` bytes and
    16-bit PNG ``depth`` bytes (with ``depth_scale``) travel untouched either way. The service folds
    the same frame from all of them.
    """
    if codec not in FRAME_CODECS:
        raise ValueError(f"codec: expected one of {list(FRAME_CODECS)}, got {codec!r}")
    array_codec = "zstd" if codec == "compact" else "raw"
    if isinstance(rgb, (bytes, bytearray)):
        rgb = bytes(rgb)
    elif codec == "compact" and np.asarray(rgb).dtype == np.uint8 and np.ndim(rgb) == 3:
        rgb = encode_png(np.asarray(rgb))
    else:
        rgb = encode_array(rgb)
    msg: dict = {"rgb": rgb, "K": _matrix(K, (3, 3)), "c2w": _matrix(c2w, (4, 4))}
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
    for name, value in (("depth_std", depth_std), ("features", features), ("labels", labels)):
        if value is not None:  # float maps gain little from lossless compression: they travel as they are
            value = np.asarray(value)
            msg[name] = encode_array(value if value.dtype == np.float16 else value.astype(np.float32))
    if frame_id is not None:
        msg["frame_id"] = str(frame_id)
    return pack(msg)


# zlib's fastest level: a colour frame packs nearly as small as at the default level in a fraction
# of its time (the client's CPU is often the service's too)
PNG_LEVEL = 1


def encode_png(rgb: np.ndarray) -> bytes:  # [H, W, 3] uint8 -> PNG bytes
    """A colour image as a lossless PNG at a fast compression level (`PNG_LEVEL`)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb, np.uint8)).save(buf, format="PNG", compress_level=PNG_LEVEL)
    return buf.getvalue()


class DownscaledFrame(UserWarning):
    """A frame without depth was over the service's limit for such frames and was sent downscaled."""


def scaled_intrinsics(K, sx: float, sy: float) -> np.ndarray:  # [3, 3] float64
    """``K`` of the image resized by ``sx`` across and ``sy`` down. Pixel centres sit on integers (the
    convention of `canonical_core.camera`: pixel u spans u - 0.5 .. u + 0.5), so the image's edges
    stay its edges: c' + 0.5 = (c + 0.5) s, as `Camera.scaled` does with one factor.

    Example:
        >>> scaled_intrinsics([[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], 0.5, 0.5)[:2].tolist()
        [[250.0, 0.0, 159.5], [0.0, 250.0, 119.5]]
    """
    K = np.array(_matrix(K, (3, 3)))
    K[0] *= sx
    K[1] *= sy
    K[0, 2] += 0.5 * sx - 0.5
    K[1, 2] += 0.5 * sy - 0.5
    return K


def _rgb_size(rgb) -> tuple[int, int]:  # (width, height) of an array, or of PNG/JPEG bytes from their header
    if isinstance(rgb, (bytes, bytearray)):
        from PIL import Image

        with Image.open(io.BytesIO(bytes(rgb))) as image:
            return image.size
    shape = np.shape(rgb)
    return (shape[1], shape[0]) if len(shape) == 3 else (0, 0)  # not an image: the service names the problem


def fit_rgb_only(rgb, K, max_pixels: int) -> tuple[object, object]:
    """``(rgb, K)`` of a frame without depth, fitted to ``max_pixels``: as they are when within it,
    else the image area-averaged down to the largest size within it (aspect kept) and K scaled to
    match (`scaled_intrinsics`), with a `DownscaledFrame` warning."""
    width, height = _rgb_size(rgb)
    if width * height <= max_pixels:
        return rgb, K
    from PIL import Image

    factor = math.sqrt(max_pixels / (width * height))
    size = (max(1, int(width * factor)), max(1, int(height * factor)))  # rounded down: within the limit
    if isinstance(rgb, (bytes, bytearray)):
        image = Image.open(io.BytesIO(bytes(rgb))).convert("RGB")
    else:
        image = Image.fromarray(np.ascontiguousarray(rgb, np.uint8))
    warnings.warn(f"rgb: a frame without depth of {width}x{height} pixels is over the service's limit of {max_pixels} "
                  f"pixels for such frames; sent downscaled to {size[0]}x{size[1]}, with K scaled to match (or send "
                  f"depth)", DownscaledFrame, stacklevel=4)  # the caller of `Session.add_frame`
    return np.asarray(image.resize(size, Image.BOX)), scaled_intrinsics(K, size[0] / width, size[1] / height)


def is_class_map(labels) -> bool:
    """Whether ``labels`` is a class map (integer or boolean [H, W]: one class id a pixel), not scores."""
    labels = np.asarray(labels)
    return labels.ndim == 2 and (np.issubdtype(labels.dtype, np.integer) or labels.dtype == np.bool_)


def label_scores(class_map, num_classes: int) -> np.ndarray:  # [H, W] ids -> [H, W, K] float16
    """A class map as the per-pixel label scores the service fuses: one-hot over K = ``num_classes``
    (a negative id: no class, every score 0). float16 holds 0 and 1 exactly in half the bytes.
    ValueError naming K when an id does not fit.

    Example:
        >>> label_scores(np.array([[0, 2], [-1, 1]]), 3)[0].tolist()
        [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    ids = np.asarray(class_map)
    top = int(ids.max()) if ids.size else -1
    if top >= num_classes:
        raise ValueError(f"labels: class {top} does not fit K = {num_classes} label classes (ids 0..{num_classes - 1}); "
                         "a session's K is fixed by its first labelled frame: pass num_classes= with that frame")
    return (ids[..., None] == np.arange(num_classes)).astype(np.float16)


def _write(path: str | os.PathLike, data: bytes) -> Path:
    """``data`` to ``path`` by way of a temporary file beside it, so a failed download leaves no half file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


class Session:
    """One session of a `Client`; get it from `Client.create_session` or `Client.session`.

    ``label_dim`` is the session's label channels (K; 0 before its first labelled frame) where the
    client knows it, else None (read from the service when a class map needs it)."""

    def __init__(self, client: "Client", session_id: str, label_dim: int | None = None):
        self.client, self.id, self.label_dim = client, session_id, label_dim

    @property
    def _path(self) -> str:
        return f"/v1/sessions/{self.id}"

    def add_frame(self, rgb, K, c2w, depth=None, depth_std=None, features=None, labels=None, frame_id=None,
                  depth_scale=None, num_classes: int | None = None, downscale: bool = True,
                  codec: FrameCodec = "compact") -> dict:
        """Fold one frame. ``rgb`` uint8 [H,W,3] array or PNG/JPEG bytes; ``K`` 3x3; ``c2w`` 4x4 OpenCV
        camera-to-world; ``depth`` float [H,W] metres, or a sensor's integer [H,W] depth (0 = missing)
        or its 16-bit PNG bytes, with ``depth_scale`` its units per metre (1000 for millimetres);
        ``depth_std`` float [H,W]; ``features`` float [H',W',C]. Returns the fold report
        (frame_index, new_voxels, ...). ``codec``: how arrays travel (`frame_body`; by default
        "compact": compressed, lossless).

        ``labels``: per-pixel label scores, float [H',W',K], or a class map, integer [H',W'] (one
        class id a pixel, negative for none), sent as one-hot scores over K = ``num_classes``, else
        the session's label channels, else (its first labelled frame) the map's largest id + 1.

        With ``downscale``, a frame without depth that is over the service's limit for such frames
        (`Client.limits`) is sent downscaled to it, K scaled to match, with a `DownscaledFrame`
        warning; without, the service refuses it (413). To stream many frames, `add_frames` keeps
        several in flight."""
        return self._post_frame(dict(rgb=rgb, K=K, c2w=c2w, depth=depth, depth_std=depth_std, features=features,
                                     labels=labels, frame_id=frame_id, depth_scale=depth_scale, num_classes=num_classes,
                                     downscale=downscale, codec=codec))

    def add_frames(self, frames: Iterable[dict], in_flight: int = 3, first_index: int | None = None) -> Iterator[dict]:
        """Fold a stream of frames, each the keyword arguments of `add_frame`, with up to ``in_flight``
        of them encoded and posted at once (threads sharing the client's keep-alive connections);
        yields their fold reports in order.

        Each frame carries its place in the session's stream (header ``Frame-Index``: ``first_index``,
        by default the session's frame count, then one more a frame), and the service folds them in
        that order whatever order they arrive in, so the scene is the one that posting them one by
        one gives. A refused frame stops the stream: `StreamRefused` (the refusal's status, code and
        field) says which frame it was and how many were acknowledged (the reports yielded); the
        frames posted after it are not folded. ``frames`` is read lazily, ``in_flight`` ahead."""
        if isinstance(in_flight, bool) or not isinstance(in_flight, int) or in_flight < 1:
            raise ValueError(f"in_flight: expected a positive integer, got {in_flight!r}")
        index = self.stats()["frames"] if first_index is None else int(first_index)
        pool = ThreadPoolExecutor(max_workers=in_flight, thread_name_prefix="canonical-frames")
        pending: collections.deque = collections.deque()
        acknowledged = 0
        try:
            for position, frame in enumerate(itertools.chain(frames, [None])):
                if frame is not None:
                    pending.append(pool.submit(self._post_frame, frame, index + position))
                # the first frame goes alone: where an earlier stream's frame was refused, the frames
                # after it are refused until a frame takes its place
                while pending and (frame is None or len(pending) >= (in_flight if position else 1)):
                    try:
                        report = pending[0].result()
                    except CanonicalError as exc:
                        raise StreamRefused(exc, index + acknowledged, acknowledged) from exc
                    pending.popleft()
                    acknowledged += 1
                    yield report
        finally:
            # frames not yet posted are dropped; posted ones finish (the service answers them, in order)
            pool.shutdown(wait=True, cancel_futures=True)

    def _post_frame(self, frame: dict, index: int | None = None) -> dict:
        """POST one frame (`add_frame`'s keyword arguments), with its ``Frame-Index`` when given."""
        frame = dict(frame)
        num_classes, downscale = frame.pop("num_classes", None), frame.pop("downscale", True)
        if frame.get("labels") is not None:
            frame["labels"] = self._label_scores(frame["labels"], num_classes)
        if frame.get("depth") is None and downscale:
            limit = self.client.limits().get("max_rgb_only_pixels")
            if limit is not None:
                frame["rgb"], frame["K"] = fit_rgb_only(frame["rgb"], frame["K"], limit)
        headers = {"Content-Type": MSGPACK} | ({} if index is None else {"Frame-Index": str(index)})
        report = self.client._request("POST", f"{self._path}/frames", content=frame_body(**frame), headers=headers).json()
        if frame.get("labels") is not None:
            self.label_dim = int(np.shape(frame["labels"])[-1])
        return report

    def _label_scores(self, labels, num_classes: int | None):
        """``labels`` as scores [H',W',K] (a class map one-hot encoded); ValueError naming K when they
        disagree with the session's K."""
        known = self.label_dim
        if is_class_map(labels):
            if num_classes is None:
                known = self.stats()["label_dim"] if known is None else known
                num_classes = known or int(np.asarray(labels, np.int64).max(initial=-1)) + 1
            if num_classes < 1:
                raise ValueError("labels: the class map holds no class id (all negative) and K is not known yet: "
                                 "pass num_classes=")
            limit = self.client.limits().get("max_label_channels")
            if limit is not None and num_classes > limit:  # before a one-hot of that many channels is built
                raise ValueError(f"labels: K = {num_classes} label classes exceed the service's limit of {limit} "
                                 "label channels")
            labels = label_scores(labels, num_classes)
        channels = np.shape(labels)[-1] if np.ndim(labels) == 3 else None
        if known and channels is not None and channels != known:
            raise ValueError(f"labels: {channels} label channels, but this session's labels have K = {known} "
                             "(fixed by its first labelled frame)")
        return labels

    def update_poses(self, poses: dict, remove=(), wait: bool = True, progress=None, poll: float = 0.5) -> dict:
        """Correct poses (``{frame key: 4x4 c2w}``) and/or remove frames (``remove``: keys), as one
        re-fold of the session's archived frames. A key is a frame's ``frame_id``, or its arrival
        index for frames sent without one. Returns what changed (frames, corrected, removed, ...).

        A long re-fold runs in the service's background (it answers 202): with ``wait`` this polls its
        status every ``poll`` seconds, calling ``progress(status)`` each time, until it is done;
        without, the service answers at once and this returns the status (``correction_id``, ``state``;
        see `correction`). Raises CanonicalError (field ``correction_id``) if the re-fold failed."""
        body = {"poses": {str(k): _matrix(c2w, (4, 4)) for k, c2w in poses.items()}, "remove": [str(k) for k in remove],
                "wait": bool(wait)}
        for k, c2w in body["poses"].items():
            if not np.isfinite(c2w).all():  # JSON has no NaN: say which pose, as the service would
                raise ValueError(f"poses.{k}: contains NaN or inf")
        return self._finished(self.client._request("POST", f"{self._path}/poses", json=body), wait, progress, poll)

    def remove_frame(self, frame_id, wait: bool = True, progress=None, poll: float = 0.5) -> dict:
        """Remove one frame (its ``frame_id`` or arrival index) from the session's scene (``wait``,
        ``progress``, ``poll``: as for `update_poses`)."""
        r = self.client._request("DELETE", f"{self._path}/frames/{quote(str(frame_id), safe='')}")
        return self._finished(r, wait, progress, poll)

    def correction(self, correction_id: str) -> dict:
        """A background correction's status: ``state`` (pending, running, done, failed), ``refolded``
        of ``total`` frames, and once done its ``result``."""
        return self.client._request("GET", f"{self._path}/corrections/{quote(correction_id, safe='')}").json()

    def _finished(self, r: httpx.Response, wait: bool, progress, poll: float) -> dict:
        """A correction's answer: as it came (200, or 202 without ``wait``), else its polled result."""
        status = r.json()
        if r.status_code != 202 or not wait:
            return status
        while True:
            if progress is not None:
                progress(status)
            if status["state"] == "done":
                return status["result"]
            if status["state"] == "failed":
                raise CanonicalError(409, "correction_failed", status["error"] or "the re-fold failed", "correction_id")
            time.sleep(poll)
            status = self.correction(status["correction_id"])

    def render(self, K, c2w, width: int, height: int, max_gaussians: int | None = None, background=None,
               colour: str | None = None, depth: str | None = None) -> dict:
        """{"rgb": uint8 [H,W,3], "depth": float32 [H,W], "alpha": float32 [H,W]}; ``colour``
        "normalised" (the service's default) or "composited", ``depth`` "median" (the service's
        default) or "expected" (see `canonical_core.rendering.render`)."""
        return self._arrays("render", _view(K, c2w, width, height, max_gaussians, background, colour, depth))

    def render_png(self, K, c2w, width: int, height: int, max_gaussians: int | None = None, background=None,
                   colour: str | None = None) -> bytes:
        body = _view(K, c2w, width, height, max_gaussians, background, colour)
        return self.client._request("POST", f"{self._path}/render", json=body, headers={"Accept": "image/png"}).content

    def features(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> dict:
        """{"features": float16 [H,W,C], "alpha": float32 [H,W]}."""
        return self._arrays("features", _view(K, c2w, width, height, max_gaussians, None))

    def features_preview_png(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> bytes:
        return self.client._request("POST", f"{self._path}/features", params={"preview": "png"},
                                    json=_view(K, c2w, width, height, max_gaussians, None)).content

    def segmentation(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> dict:
        """{"labels": uint16 [H,W] (65535 where nothing is drawn), "alpha": float32 [H,W]}."""
        return self._arrays("segmentation", _view(K, c2w, width, height, max_gaussians, None))

    def segmentation_png(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> bytes:
        return self.client._request("POST", f"{self._path}/segmentation", json=_view(K, c2w, width, height, max_gaussians, None),
                                    headers={"Accept": "image/png"}).content

    def _arrays(self, route: str, body: dict) -> dict:
        r = self.client._request("POST", f"{self._path}/{route}", json=body, headers={"Accept": MSGPACK})
        return {k: decode_array(v, k) for k, v in unpack(r.content, route).items()}

    def export_ply(self, path: str | os.PathLike, max_gaussians: int | None = None) -> Path:
        return self._export(".ply", path, max_gaussians)

    def export_splat(self, path: str | os.PathLike, max_gaussians: int | None = None) -> Path:
        return self._export(".splat", path, max_gaussians)

    def export_mesh(self, path: str | os.PathLike, min_support: float | None = None) -> Path:
        """The surface as a coloured triangle mesh (binary PLY: vertex x, y, z, red, green, blue; faces)."""
        params = {} if min_support is None else {"min_support": float(min_support)}
        return _write(path, self.client._request("GET", f"{self._path}/mesh.ply", params=params).content)

    def _export(self, suffix: str, path, max_gaussians) -> Path:
        params = {} if max_gaussians is None else {"max_gaussians": int(max_gaussians)}
        return _write(path, self.client._request("GET", f"{self._path}/gaussians{suffix}", params=params).content)

    def stats(self) -> dict:
        return self.client._request("GET", self._path).json()

    def digest(self) -> dict:
        return self.client._request("GET", f"{self._path}/digest").json()

    def delete(self) -> None:
        self.client._request("DELETE", self._path)

    def __repr__(self) -> str:
        return f"Session({self.id!r})"


def default_url() -> str:
    """The service's base URL when none is given: ``CANONICAL_URL`` from the environment, else the
    address `canonical serve` listens on by default."""
    return os.environ.get("CANONICAL_URL") or "http://127.0.0.1:8000"


class Client:
    """A connection to the service.

    Args:
        url: base URL, e.g. ``http://127.0.0.1:8000`` (default: `default_url`, as the CLI's ``--url``,
            so that scripts and the CLI find the same service).
        token: bearer token (default: ``CANONICAL_API_TOKEN`` from the environment, if set).
        timeout: seconds per request.
        max_retries: how often a 429 is retried (waiting its Retry-After, at most ``max_wait`` s each).
    """

    def __init__(self, url: str | None = None, token: str | None = None, timeout: float = 120.0, max_retries: int = 8,
                 max_wait: float = 10.0):
        url = url if url is not None else default_url()
        token = token if token is not None else os.environ.get("CANONICAL_API_TOKEN") or None
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.max_retries, self.max_wait = max_retries, max_wait
        self._limits: dict | None = None

    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        for attempt in range(self.max_retries + 1):
            r = self._http.request(method, path, **kwargs)
            if r.status_code != 429 or attempt == self.max_retries:
                break
            time.sleep(self._retry_after(r, attempt))
        if r.status_code >= 400:
            raise self._error(r)
        return r

    def _retry_after(self, r: httpx.Response, attempt: int) -> float:
        try:
            wait = float(r.headers.get("Retry-After", ""))
        except ValueError:
            wait = 0.25 * 2**attempt
        return min(self.max_wait, wait if math.isfinite(wait) and wait >= 0 else 1.0)

    @staticmethod
    def _error(r: httpx.Response) -> CanonicalError:
        try:
            err = r.json()["error"]
            return CanonicalError(r.status_code, err.get("code", "error"), err.get("message", ""), err.get("field"))
        except (ValueError, KeyError, TypeError):
            return CanonicalError(r.status_code, "error", r.text[:500])

    def create_session(self, voxel_size: float | None = None, **settings) -> Session:
        """A new session; ``settings`` are the service's session settings (SceneConfig's public fields:
        max_voxels, sh_degree, ..., groups as dicts, e.g. ``range={"near": 0.2}, sensor={"family": "hololens"}``).
        Without ``voxel_size`` the service chooses it from the first frame with depth (its stats say which)."""
        body = settings if voxel_size is None else {"voxel_size": voxel_size, **settings}
        r = self._request("POST", "/v1/sessions", json=body)
        return Session(self, r.json()["id"], label_dim=0)

    def session(self, session_id: str) -> Session:
        """An existing session (checked: raises CanonicalError 404 when unknown)."""
        stats = self._request("GET", f"/v1/sessions/{session_id}").json()
        return Session(self, session_id, label_dim=stats.get("label_dim"))

    def limits(self) -> dict:
        """The service's request limits (``GET /v1/limits``: ``max_rgb_only_pixels``, ``max_image_pixels``,
        ...), read once per client; {} from a service that does not publish them."""
        if self._limits is None:
            try:
                self._limits = self._request("GET", "/v1/limits").json()
            except CanonicalError as exc:
                if exc.status != 404:
                    raise
                self._limits = {}
        return self._limits

    def sessions(self) -> list[dict]:
        return self._request("GET", "/v1/sessions").json()["sessions"]

    def prune_sessions(self, dry_run: bool = False) -> dict:
        """Apply the service's retention policy now (``POST /v1/sessions/prune``); with ``dry_run`` only
        list what it would remove. Returns its report (``removed``: the sessions, oldest first)."""
        return self._request("POST", "/v1/sessions/prune", params={"dry_run": "true" if dry_run else "false"}).json()

    def health(self) -> dict:
        return self._request("GET", "/healthz").json()

    def metrics(self) -> str:
        return self._request("GET", "/metrics").text

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def png_to_array(data: bytes) -> np.ndarray:
    """PNG bytes -> numpy (uint8 [H,W,3] for colour, [H,W] for palette/grey)."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)))
