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

import io
import math
import numbers
import os
import time
from pathlib import Path
from urllib.parse import quote

import httpx
import numpy as np

from canonical_wire import decode_array, encode_array, pack, unpack  # the codec the service uses too

MSGPACK = "application/msgpack"


class CanonicalError(Exception):
    """A 4xx/5xx answer: ``status``, ``code``, ``message`` and the offending ``field`` (or None)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None):
        super().__init__(f"{status} {code}: {message}")
        self.status, self.code, self.message, self.field = status, code, message, field


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


def sensor_depth(depth, depth_scale) -> np.ndarray:  # [H, W] integers -> [H, W] uint16
    """A sensor's integer depth as the 16-bit array it travels as; ValueError (naming the field) for a
    missing or non-positive ``depth_scale`` or values outside 0..65535."""
    if isinstance(depth_scale, bool) or not isinstance(depth_scale, numbers.Real) or not depth_scale > 0 \
            or not math.isfinite(depth_scale):
        raise ValueError(f"depth_scale: integer depth needs its units per metre (e.g. 1000 for millimetres), got {depth_scale!r}")
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
               depth_scale=None) -> bytes:
    """The msgpack body of one frame as `Session.add_frame` sends it (its arguments, the same checks)."""
    msg: dict = {"rgb": bytes(rgb) if isinstance(rgb, (bytes, bytearray)) else encode_array(rgb),
                 "K": _matrix(K, (3, 3)), "c2w": _matrix(c2w, (4, 4))}
    if depth is not None and np.issubdtype(np.asarray(depth).dtype, np.integer):
        msg["depth"], msg["depth_scale"] = encode_array(sensor_depth(depth, depth_scale)), float(depth_scale)
        depth = None
    elif depth_scale is not None:  # a float depth is in metres already: a scale would be applied twice or ignored
        raise ValueError("depth_scale: only with integer depth (sensor units); float depth is in metres")
    for name, value in (("depth", depth), ("depth_std", depth_std), ("features", features), ("labels", labels)):
        if value is not None:
            value = np.asarray(value)
            msg[name] = encode_array(value if value.dtype == np.float16 else value.astype(np.float32))
    if frame_id is not None:
        msg["frame_id"] = str(frame_id)
    return pack(msg)


class Session:
    """One session of a `Client`; get it from `Client.create_session` or `Client.session`."""

    def __init__(self, client: "Client", session_id: str):
        self.client, self.id = client, session_id

    @property
    def _path(self) -> str:
        return f"/v1/sessions/{self.id}"

    def add_frame(self, rgb, K, c2w, depth=None, depth_std=None, features=None, labels=None, frame_id=None,
                  depth_scale=None) -> dict:
        """Fold one frame. ``rgb`` uint8 [H,W,3] array or PNG/JPEG bytes; ``K`` 3x3; ``c2w`` 4x4 OpenCV
        camera-to-world; ``depth`` float [H,W] metres, or a sensor's integer [H,W] depth (0 = missing)
        with ``depth_scale`` its units per metre (1000 for millimetres), which travels as 16-bit;
        ``depth_std`` float [H,W]; ``features`` / ``labels`` float [H',W',C]. Returns the fold report
        (frame_index, new_voxels, ...)."""
        body = frame_body(rgb, K, c2w, depth, depth_std, features, labels, frame_id, depth_scale)
        return self.client._request("POST", f"{self._path}/frames", content=body, headers={"Content-Type": MSGPACK}).json()

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

    def _export(self, suffix: str, path, max_gaussians) -> Path:
        params = {} if max_gaussians is None else {"max_gaussians": int(max_gaussians)}
        data = self.client._request("GET", f"{self._path}/gaussians{suffix}", params=params).content
        path = Path(path)
        tmp = path.with_name(path.name + ".part")
        tmp.write_bytes(data)
        os.replace(tmp, path)
        return path

    def stats(self) -> dict:
        return self.client._request("GET", self._path).json()

    def digest(self) -> dict:
        return self.client._request("GET", f"{self._path}/digest").json()

    def delete(self) -> None:
        self.client._request("DELETE", self._path)

    def __repr__(self) -> str:
        return f"Session({self.id!r})"


class Client:
    """A connection to the service.

    Args:
        url: base URL, e.g. ``http://127.0.0.1:8000``.
        token: bearer token (default: ``CANONICAL_API_TOKEN`` from the environment, if set).
        timeout: seconds per request.
        max_retries: how often a 429 is retried (waiting its Retry-After, at most ``max_wait`` s each).
    """

    def __init__(self, url: str, token: str | None = None, timeout: float = 120.0, max_retries: int = 8, max_wait: float = 10.0):
        token = token if token is not None else os.environ.get("CANONICAL_API_TOKEN") or None
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=url.rstrip("/"), headers=headers, timeout=timeout)
        self.max_retries, self.max_wait = max_retries, max_wait

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

    def create_session(self, voxel_size: float, **settings) -> Session:
        """A new session; ``settings`` are the service's session settings (SceneConfig's public fields:
        max_voxels, sh_degree, ..., groups as dicts, e.g. ``range={"near": 0.2}, free_space={"margin": 3.0}``)."""
        r = self._request("POST", "/v1/sessions", json={"voxel_size": voxel_size, **settings})
        return Session(self, r.json()["id"])

    def session(self, session_id: str) -> Session:
        """An existing session (checked: raises CanonicalError 404 when unknown)."""
        self._request("GET", f"/v1/sessions/{session_id}")
        return Session(self, session_id)

    def sessions(self) -> list[dict]:
        return self._request("GET", "/v1/sessions").json()["sessions"]

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
