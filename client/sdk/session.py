"""`Session`: one session of a `Client`: frames in (one, or a stream with several in flight), pose
corrections, renders, features, segmentation, exports and live fold events out."""

from __future__ import annotations

import functools
import json
import secrets
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Iterator
from urllib.parse import quote

import httpx
import numpy as np

from canonical_wire import decode_array, unpack

from .errors import CanonicalError, ServiceUnreachable
from .frames import MSGPACK, FrameCodec, fit_rgb_only, frame_body, is_class_map, wire_matrix
from .stream import stream_frames

if TYPE_CHECKING:
    from .client import Client


def _whole(value, name: str) -> int:
    """``value`` as an int (an integer of any kind, or a float that is one); ValueError naming ``name``
    where it is not a whole number."""
    if isinstance(value, bool) or not (hasattr(value, "__index__") or (isinstance(value, float) and value.is_integer())):
        raise ValueError(f"{name}: expected a whole number, got {value!r}")
    return int(value)


def _arrival(key) -> bool:
    """Whether a frame key is an arrival index: an integer (numpy's too), not a bool or a string."""
    return hasattr(key, "__index__") and not isinstance(key, (bool, np.bool_))


def _json_matrix(m, shape: tuple[int, int], name: str) -> list:
    """`wire_matrix` for a JSON body, which has no NaN: ValueError naming ``name`` for one, as the
    service would name it."""
    rows = wire_matrix(m, shape, name)
    if not np.isfinite(rows).all():
        raise ValueError(f"{name}: contains NaN or inf")
    return rows


def _view(K, c2w, width: int, height: int, max_gaussians: int | None, background, colour: str | None = None,
          depth: str | None = None) -> dict:
    """A view's JSON body; ValueError naming the field for what JSON or the service would refuse
    unnamed (NaN in a matrix, a width that is no number)."""
    body = {"K": _json_matrix(K, (3, 3), "K"), "c2w": _json_matrix(c2w, (4, 4), "c2w"), "width": _whole(width, "width"),
            "height": _whole(height, "height")}
    if colour is not None:
        body["colour"] = colour
    if depth is not None:
        body["depth"] = depth
    if max_gaussians is not None:
        body["max_gaussians"] = _whole(max_gaussians, "max_gaussians")
    if background is not None:
        if np.shape(background) != (3,) or not np.isfinite(np.asarray(background, np.float64)).all():
            raise ValueError(f"background: expected 3 finite numbers (RGB in [0, 1]), got {background!r}")
        body["background"] = [float(x) for x in background]
    return body


def path_segment(value, name: str) -> str:
    """``value`` (a session, frame or correction id) as one segment of a request's path: percent-encoded
    whole, so a '/' or '?' in it stays in it, and the dot segments '.' and '..' as %2E, which the HTTP
    client would otherwise resolve against the path before them (``..`` naming the session itself).
    ValueError naming ``name`` for an empty id, which names no resource.

    Example:
        >>> path_segment("a/b", "frame_id"), path_segment("..", "frame_id")
        ('a%2Fb', '%2E%2E')
    """
    text = str(value)
    if not text:
        raise ValueError(f"{name}: expected an id, got an empty string")
    return "%2E" * len(text) if text in (".", "..") else quote(text, safe="")


def _write(path: str | os.PathLike, chunks: Iterable[bytes]) -> Path:
    """A download's ``chunks`` to ``path`` as they arrive, by way of a temporary file beside it, so a
    failed download leaves no half file; the temporary file is removed if the write fails, and the
    error names ``path``, not it. Missing parent folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a name of its own, so that downloads to one path at once never write or move each other's file;
    # made as open() makes files (the umask's mode, where mkstemp's would be private)
    tmp = path.with_name(f"{path.name}.{secrets.token_hex(6)}.part")
    try:
        with open(tmp, "xb") as f:
            for chunk in chunks:
                f.write(chunk)
        os.replace(tmp, path)
    except BaseException as exc:  # Ctrl-C too: no half file of the download's size left behind
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename in (str(tmp), tmp) and exc.errno is not None:
            raise type(exc)(exc.errno, exc.strerror, str(path)) from None
        raise
    return path


class Session:
    """One session of a `Client`; get it from `Client.create_session` or `Client.session`.

    ``label_dim`` is the session's label channels (K; 0 before its first labelled frame) where the
    client knows it, else None (read from the service when a class map needs it)."""

    def __init__(self, client: "Client", session_id: str, label_dim: int | None = None):
        self.client, self.id, self.label_dim = client, session_id, label_dim

    @property
    def _path(self) -> str:
        return f"/v1/sessions/{path_segment(self.id, 'session_id')}"

    def add_frame(self, rgb, K, c2w, depth=None, depth_std=None, features=None, labels=None, frame_id=None,
                  depth_scale=None, num_classes: int | None = None, downscale: bool = True,
                  codec: FrameCodec = "compact") -> dict:
        """Fold one frame. ``rgb`` uint8 [H,W,3] array or PNG/JPEG bytes; ``K`` 3x3; ``c2w`` 4x4 OpenCV
        camera-to-world; ``depth`` float [H,W] metres, or a sensor's integer [H,W] depth (0 = missing)
        or its 16-bit PNG bytes, with ``depth_scale`` its units per metre (1000 for millimetres), at
        the image's resolution or registered to it at a lower one (a phone's LiDAR: the frame is folded
        at the depth's pixels, the colour area-averaged to them, which the SDK does before it sends the
        colour, array or image bytes: a fraction of the bytes);
        ``depth_std`` float [H,W]; ``features`` float [H',W',C]. Returns the fold report
        (frame_index, new_voxels, ...). ``codec``: how arrays travel (`frame_body`; by default
        "compact": compressed, lossless).

        ``labels``: per-pixel label scores, float [H',W',K], or a class map, integer [H',W'] (one
        class id a pixel, negative for none), fused as one-hot scores over K = ``num_classes``, else
        the session's label channels, else (its first labelled frame) the map's largest id + 1. A
        class map travels as its ids (with K), not one-hot. A class map PNG's bytes (0 no class, k + 1
        class k, as label files hold them) travel as they are, with ``num_classes`` (or the session's K).

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
        one gives. A frame whose ``frame_id`` the session holds already is answered with its report
        (its ``frame_index`` the place it holds) and takes no new place: the frames from the first go
        alone until one takes a new place, so a stream resumed from a point before the last frame the
        session holds skips those it holds. A frame that repeats the ``frame_id`` of an earlier frame of
        the same stream is posted once that one is answered and answered as it (a replay; 409 where its
        content differs), taking no place. A refused frame stops the stream: `StreamRefused` (the
        refusal's status, code and field) says which frame it was and how many were acknowledged (the
        reports yielded); the frames posted after it are not folded. A frame the client cannot send
        (its arguments refused by the SDK's own checks, the service unreachable) stops it too, with
        `StreamStopped` (the error as its cause), before any frame after it is posted. ``frames`` is
        read lazily, ``in_flight`` ahead."""
        if isinstance(in_flight, bool) or not isinstance(in_flight, int) or in_flight < 1:
            raise ValueError(f"in_flight: expected a positive integer, got {in_flight!r}")
        return stream_frames(self, frames, in_flight, first_index)

    def _post_frame(self, frame: dict, index: int | None = None) -> dict:
        """POST one frame (`add_frame`'s keyword arguments), with its ``Frame-Index`` when given."""
        return self._send_frame(*self._frame_body(frame), index)

    def _frame_body(self, frame: dict) -> tuple[bytes, dict]:
        """A frame's body (`add_frame`'s keyword arguments checked and encoded) and the arguments it was
        made of (K as sent, ``num_classes`` found)."""
        frame = dict(frame)
        downscale = frame.pop("downscale", True)
        if frame.get("labels") is not None:
            frame["num_classes"] = self._label_classes(frame["labels"], frame.get("num_classes"))
        if frame.get("depth") is None and downscale:
            limit = self.client.limits().get("max_rgb_only_pixels")
            if limit is not None:
                frame["rgb"], frame["K"] = fit_rgb_only(frame["rgb"], frame["K"], limit)
        return frame_body(**frame), frame

    def _send_frame(self, body: bytes, frame: dict, index: int | None) -> dict:
        """POST a built frame ``body`` (`_frame_body`), at stream place ``index`` when given."""
        headers = {"Content-Type": MSGPACK} | ({} if index is None else {"Frame-Index": str(index)})
        report = self.client._request("POST", f"{self._path}/frames", idempotent=frame.get("frame_id") is not None,
                                      content=body, headers=headers).json()
        if frame.get("labels") is not None:
            self.label_dim = frame["num_classes"] or int(np.shape(frame["labels"])[-1])
        return report

    def _label_classes(self, labels, num_classes: int | None) -> int | None:
        """A class map's K (None for scores, which carry theirs); ValueError naming K when the labels
        disagree with the session's K."""
        known = self.label_dim
        if isinstance(labels, (bytes, bytearray)):  # a class map PNG: its K is not in its pixels
            num_classes = num_classes or known or self.stats()["label_dim"] or None
            if num_classes is None:
                raise ValueError("num_classes: required with a class map PNG while the session's K is not known yet")
            channels = num_classes
        elif is_class_map(labels):
            if num_classes is None:
                known = self.stats()["label_dim"] if known is None else known
                num_classes = known or int(np.asarray(labels, np.int64).max(initial=-1)) + 1
            if num_classes < 1:
                raise ValueError("labels: the class map holds no class id (all negative) and K is not known yet: "
                                 "pass num_classes=")
            channels = num_classes
        else:
            channels, num_classes = (np.shape(labels)[-1] if np.ndim(labels) == 3 else None), None
        if known and channels is not None and channels != known:
            raise ValueError(f"labels: {channels} label channels, but this session's labels have K = {known} "
                             "(fixed by its first labelled frame)")
        return num_classes

    def update_poses(self, poses: dict, remove=(), wait: bool = True, progress=None, poll: float = 0.5) -> dict:
        """Correct poses (``{frame key: 4x4 c2w}``) and/or remove frames (``remove``: keys), as one
        re-fold of the session's archived frames. A key that is an integer is an arrival index (as in
        the library); a string is a ``frame_id``, else, where it is digits no frame has as its
        ``frame_id``, an arrival index. Returns what changed (frames, corrected, removed, ...).

        A long re-fold runs in the service's background (it answers 202): with ``wait`` this polls its
        status every ``poll`` seconds, calling ``progress(status)`` each time, until it is done;
        without, the service answers at once and this returns the status (``correction_id``, ``state``;
        see `correction`). Raises CanonicalError (field ``correction_id``) if the re-fold failed."""
        if isinstance(remove, (str, bytes)):  # one key, which a list of its characters would not mean
            raise ValueError(f"remove: expected a list of frame keys, got the {type(remove).__name__} {remove!r}")
        by_id = {str(k): _json_matrix(c2w, (4, 4), f"poses.{k}") for k, c2w in poses.items() if not _arrival(k)}
        by_arrival = {str(int(k)): _json_matrix(c2w, (4, 4), f"poses.{k}") for k, c2w in poses.items() if _arrival(k)}
        body = {"poses": by_id, "remove": [int(k) if _arrival(k) else str(k) for k in remove], "wait": bool(wait)}
        if by_arrival:  # a service of before this field took every key as a string
            body["poses_by_arrival"] = by_arrival
        return self._finished(self.client._request("POST", f"{self._path}/poses", json=body), wait, progress, poll)

    def remove_frame(self, frame_id, wait: bool = True, progress=None, poll: float = 0.5) -> dict:
        """Remove one frame (its ``frame_id``, or its arrival index as an integer: see `update_poses`)
        from the session's scene (``wait``, ``progress``, ``poll``: as for `update_poses`)."""
        if _arrival(frame_id):
            return self.update_poses({}, remove=[frame_id], wait=wait, progress=progress, poll=poll)
        r = self.client._request("DELETE", f"{self._path}/frames/{path_segment(frame_id, 'frame_id')}")
        return self._finished(r, wait, progress, poll)

    def correction(self, correction_id: str) -> dict:
        """A background correction's status: ``state`` (pending, running, done, failed), ``refolded``
        of ``total`` frames, and once done its ``result``."""
        return self.client._request("GET", f"{self._path}/corrections/{path_segment(correction_id, 'correction_id')}").json()

    def _finished(self, r: httpx.Response, wait: bool, progress, poll: float) -> dict:
        """A correction's answer: as it came (200, or 202 without ``wait``), else its polled result. The
        session's K is read again at its next class map: removing its labelled frames frees it."""
        self.label_dim = None
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
        """The view's colour as PNG bytes (arguments as `render`)."""
        body = _view(K, c2w, width, height, max_gaussians, background, colour)
        return self.client._request("POST", f"{self._path}/render", json=body, headers={"Accept": "image/png"},
                                    idempotent=True).content

    def features(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> dict:
        """{"features": float16 [H,W,C], "alpha": float32 [H,W]}."""
        return self._arrays("features", _view(K, c2w, width, height, max_gaussians, None))

    def features_preview_png(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> bytes:
        """The view's features as a picture (their first three principal components as RGB), PNG bytes."""
        return self.client._request("POST", f"{self._path}/features", params={"preview": "png"},
                                    json=_view(K, c2w, width, height, max_gaussians, None), idempotent=True).content

    def segmentation(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> dict:
        """{"labels": uint16 [H,W] (65535 where nothing is drawn), "alpha": float32 [H,W]}."""
        return self._arrays("segmentation", _view(K, c2w, width, height, max_gaussians, None))

    def segmentation_png(self, K, c2w, width: int, height: int, max_gaussians: int | None = None) -> bytes:
        """The view's labels as a palette PNG (index 0 nothing drawn, k + 1 label k), bytes."""
        return self.client._request("POST", f"{self._path}/segmentation", json=_view(K, c2w, width, height, max_gaussians, None),
                                    headers={"Accept": "image/png"}, idempotent=True).content

    def _arrays(self, route: str, body: dict) -> dict:
        r = self.client._request("POST", f"{self._path}/{route}", json=body, headers={"Accept": MSGPACK}, idempotent=True)
        return {k: decode_array(v, k) for k, v in unpack(r.content, route).items()}

    def export_ply(self, path: str | os.PathLike, max_gaussians: int | None = None) -> Path:
        """The scene's Gaussians as a 3DGS PLY file at ``path`` (at most ``max_gaussians``, the most
        opaque); returns the path. Written beside it first, so that a failed download leaves no half file."""
        return self._export(".ply", path, max_gaussians)

    def export_splat(self, path: str | os.PathLike, max_gaussians: int | None = None) -> Path:
        """The scene's Gaussians as a ``.splat`` file (the web viewers' 32-byte rows) at ``path``, as `export_ply`."""
        return self._export(".splat", path, max_gaussians)

    def export_mesh(self, path: str | os.PathLike, min_support: float | None = None) -> Path:
        """The surface as a coloured triangle mesh (binary PLY: vertex x, y, z, red, green, blue; faces)."""
        params = {} if min_support is None else {"min_support": float(min_support)}
        return self.client._download(f"{self._path}/mesh.ply", functools.partial(_write, path), params=params)

    def _export(self, suffix: str, path, max_gaussians) -> Path:
        params = {} if max_gaussians is None else {"max_gaussians": int(max_gaussians)}
        return self.client._download(f"{self._path}/gaussians{suffix}", functools.partial(_write, path), params=params)

    def events(self, every: float | None = None) -> Iterator[tuple[str, dict]]:
        """The session's live events as (name, fields), read from its Server-Sent Events stream:
        ``"state"`` at once (frames, voxels, label_dim), then ``"fold"`` after each acknowledged fold
        (frames, voxels, the fold report, the frame's camera) or, with ``every`` seconds, at most one
        per interval standing for the folds since the last (with ``folds``, ``cameras``,
        ``previous_time`` and ``warned``: docs/api.md, "Fold events"); the stream's last event is
        ``"deleted"`` or ``"dropped"`` (it read too slowly: open a new one for the latest state). It
        ends when the service stops or the iterator is closed. Raises `CanonicalError` when the
        service refuses the stream (e.g. 429 over its cap of open streams, 422 for a bad ``every``)."""
        params = {} if every is None else {"every": every}
        # no read timeout: a quiet session's stream sends only a comment every 15 s
        timeout = self.client._http.timeout.as_dict() | {"read": None}
        try:
            with self.client._http.stream("GET", f"{self._path}/events", params=params, timeout=httpx.Timeout(**timeout),
                                          headers={"Accept": "text/event-stream"}) as r:
                if r.status_code >= 400:
                    r.read()
                    raise self.client._error(r)
                name = "message"
                for line in r.iter_lines():
                    if line.startswith("event:"):
                        name = line[6:].strip()
                    elif line.startswith("data:"):
                        yield name, json.loads(line[5:])
                        name = "message"
        except (httpx.RemoteProtocolError, httpx.ReadError):  # the service went (killed) mid-stream: it ends
            return
        except httpx.TransportError as exc:
            raise ServiceUnreachable(f"GET {self.client._http.base_url}{self._path}/events: {type(exc).__name__}: "
                                     f"{exc or 'no answer'}") from exc

    def stats(self) -> dict:
        """The session's stats (``GET /v1/sessions/{id}``: frames, voxels, gaussians, label_dim, config, ...)."""
        return self.client._request("GET", self._path).json()

    def wait_for_colours(self, timeout: float = 120.0, poll: float = 0.25, progress=None) -> dict:
        """Wait until renders and exports of this session show colours solved for every frame it
        holds, and return its stats (`stats`). The service solves a session's colours in the
        background once its stream pauses (stats: ``colours_solved_frames`` reaches ``frames``); a
        render or an export made before then shows the fused colours. Returns at once when there is
        nothing to wait for (the solve is off: ``colour_solve.views`` 0, or no frame yet), as soon as
        a frame arrives meanwhile (a live stream: its colours are solved once it pauses), or after
        ``timeout`` seconds: the stats returned say whether the colours were solved. ``progress(stats)``
        is called before each wait of ``poll`` seconds."""
        stats, deadline = self.stats(), time.monotonic() + timeout
        frames = stats["frames"]
        while (frames and stats["config"]["colour_solve"]["views"] and stats["colours_solved_frames"] != frames
               and time.monotonic() < deadline):
            if progress is not None:
                progress(stats)
            time.sleep(poll)
            stats = self.stats()
            if stats["frames"] != frames:
                break
        return stats

    def digest(self) -> dict:
        """The scene's digest (``sha256`` of its state, and its frames): equal digests, equal scenes."""
        return self.client._request("GET", f"{self._path}/digest").json()

    def delete(self) -> None:
        """Delete the session and its files on the service."""
        self.client._request("DELETE", self._path)

    def __repr__(self) -> str:
        return f"Session({self.id!r})"
