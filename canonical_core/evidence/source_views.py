"""Source views of the plane sweep: what a frame contributes as a source (camera + matching
features, no image), how sources are chosen for a reference view (`SelectionRule`,
`select_sources`), and the bounded window of recent views a session keeps (`SourceWindow`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..frame import Frame
from .matching import matching_features, sweep_luminance

DEFAULT_SCALE = 0.5  # sweep resolution relative to the image


@dataclass(frozen=True, eq=False)
class SourceView:
    """What a frame contributes as a source of the plane sweep: no image, just geometry + features.

    Attributes:
        camera: the frame's camera at sweep resolution (``frame.camera.scaled(scale)``).
        features: int8 [h, w, L] quantised matching features at sweep resolution (F = MATCHING_SCALE * q).
        frame_id: the frame's id, if any.
        median_depth: typical depth of what the view sees (metres; NaN = unknown), used to judge
            baselines when choosing sources.
        scale: sweep resolution relative to the frame's image.
    """

    camera: Camera
    features: np.ndarray  # [h, w, L] int8
    frame_id: str | None = None
    median_depth: float = math.nan
    scale: float = DEFAULT_SCALE

    def __post_init__(self):
        f = self.features
        if not isinstance(f, np.ndarray) or f.dtype != np.int8 or f.ndim != 3:
            raise ValueError(f"features: expected an int8 numpy array [h, w, L], got "
                             f"{getattr(f, 'dtype', type(f).__name__)} {list(getattr(f, 'shape', []))}")
        if f.shape[:2] != (self.camera.height, self.camera.width):
            raise ValueError(f"features: shape {list(f.shape[:2])} does not match the sweep camera "
                             f"{self.camera.height}x{self.camera.width}")
        if min(f.shape[:2]) < 2:
            raise ValueError(f"features: the sweep resolution must be at least 2x2, got {list(f.shape[:2])}")
        object.__setattr__(self, "features", np.ascontiguousarray(f))

    @classmethod
    def from_frame(cls, frame: Frame, scale: float = DEFAULT_SCALE, depth=None) -> "SourceView":
        """Matching features of ``frame`` at ``scale`` x its resolution.

        ``depth`` (an [H, W] map in metres, or a number) sets `median_depth`; by default the
        frame's own depth is used when it has one.
        """
        if not isinstance(frame, Frame):
            raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
        if not (isinstance(scale, (int, float)) and 0 < scale <= 1):
            raise ValueError(f"scale: expected a number in (0, 1], got {scale!r}")
        cam = frame.camera.scaled(scale) if scale != 1 else frame.camera
        if min(cam.width, cam.height) < 2:
            raise ValueError(f"scale: {scale} leaves a {cam.width}x{cam.height} sweep image; need at least 2x2")
        luma = sweep_luminance(frame.rgb, (cam.height, cam.width))
        if depth is None:
            depth = frame.depth
        return cls(camera=cam, features=matching_features(luma), frame_id=frame.frame_id,
                   median_depth=_median_depth(depth), scale=float(scale))

    @property
    def nbytes(self) -> int:
        return int(self.features.nbytes)


def _median_depth(depth) -> float:
    if depth is None:
        return math.nan
    if isinstance(depth, (int, float)):
        return float(depth) if depth > 0 else math.nan
    d = np.asarray(depth.numpy() if isinstance(depth, Tensor) else depth, dtype=np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if d.size else math.nan


def _as_view(item, scale: float, field_name: str) -> SourceView:
    if isinstance(item, SourceView):
        return item
    if isinstance(item, Frame):
        return SourceView.from_frame(item, scale)
    raise ValueError(f"{field_name}: expected a Frame or a SourceView, got {type(item).__name__}")


def _on_image(camera: Camera, uv: Tensor, z: Tensor) -> Tensor:  # `Camera.project`'s [N, 2], [N] -> [N] bool
    """Projections in front of ``camera`` that land on its image."""
    u, v = uv[:, 0], uv[:, 1]
    return (z > 1e-9) & (u >= -0.5) & (u <= camera.width - 0.5) & (v >= -0.5) & (v <= camera.height - 0.5)



def _typical_depth(views: Sequence[SourceView]) -> float | None:
    """Median of the views' known typical depths (metres), None when none knows one."""
    known = [v.median_depth for v in views if math.isfinite(v.median_depth)]
    return float(np.median(known)) if known else None



@dataclass(frozen=True)
class SelectionRule:
    """How sources are chosen for a reference view (all ratios are baseline / scene depth).

    A candidate is *eligible* when its optical axis is within ``max_angle_deg`` of the reference's,
    at least ``min_overlap`` of the reference's image (a 12 x 9 grid of pixels lifted to the scene
    depth) projects into it, and its baseline ratio is within [min_ratio, max_ratio]. Eligible
    candidates score ``overlap * exp(-0.5 * (ln(ratio / target_ratio) / 0.5)^2)`` (a log-normal
    preference for ``target_ratio``) and are taken greedily, each later pick's score multiplied by
    min(1, distance to the nearest earlier pick / (target_ratio * depth)) so that two nearly
    identical views are not both taken. When fewer than k candidates are eligible, the rest are
    filled, the same way, from the candidates that overlap and have a non-zero baseline outside
    [min_ratio, max_ratio] (the first frames of a stream, a camera that barely moves, a sparse stream
    whose views two back are already beyond max_ratio): a second source at a wider baseline still
    beats none, and where the depth stays uncertain U_pos says so.

    The defaults were chosen on a real indoor capture (the evaluation's ledger has the figures):
    wider baselines change the appearance too much between views, narrower ones do not separate
    the hypotheses, and the result is flat over a range of target ratios and window capacities.
    """

    min_ratio: float = 0.04
    max_ratio: float = 0.3
    target_ratio: float = 0.16
    max_angle_deg: float = 30.0
    min_overlap: float = 0.3

    def __post_init__(self):
        for name in ("min_ratio", "max_ratio", "target_ratio", "max_angle_deg", "min_overlap"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
        if not self.min_ratio <= self.target_ratio <= self.max_ratio:
            raise ValueError(f"target_ratio: expected min_ratio <= target_ratio <= max_ratio, got "
                             f"{self.min_ratio}, {self.target_ratio}, {self.max_ratio}")
        if self.min_overlap > 1:
            raise ValueError(f"min_overlap: expected a fraction in (0, 1], got {self.min_overlap}")

    def as_array(self) -> np.ndarray:
        return np.array([self.min_ratio, self.max_ratio, self.target_ratio, self.max_angle_deg, self.min_overlap])

    @classmethod
    def from_array(cls, a) -> "SelectionRule":
        a = [float(x) for x in np.asarray(a, dtype=np.float64).ravel()]
        return cls(*a)


def _overlap(reference: Camera, candidate: Camera, depth: float, nx: int = 12, ny: int = 9) -> float:
    """Share of the reference's image that the candidate sees, for a scene at ``depth``: an
    ``nx`` x ``ny`` grid of pixel centres lifted to ``depth``, projected into the candidate."""
    us = (torch.arange(nx) + 0.5) * reference.width / nx - 0.5
    vs = (torch.arange(ny) + 0.5) * reference.height / ny - 0.5
    v, u = torch.meshgrid(vs, us, indexing="ij")
    grid = reference.lift(torch.stack([u.ravel(), v.ravel()], -1), torch.full((nx * ny,), float(depth)))
    return float(_on_image(candidate, *candidate.project(grid)).float().mean())


def _pair_geometry(reference: Camera, candidate: Camera, depth: float) -> tuple[float, float, float]:
    """(baseline / depth, angle between optical axes in degrees, overlap)."""
    a, b = reference.c2w64(), candidate.c2w64()
    ratio = float(np.linalg.norm(a[:3, 3] - b[:3, 3])) / depth
    cosang = float(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0))
    return ratio, math.degrees(math.acos(cosang)), _overlap(reference, candidate, depth)


def select_sources(
    reference: Camera,
    candidates: Sequence[Camera],
    k: int = 2,
    depth: float = 1.0,
    rule: SelectionRule | None = None,
) -> list[int]:
    """Indices of up to ``k`` candidates to sweep ``reference`` against, best first (see `SelectionRule`).

    ``depth`` is the typical depth of the scene in front of the reference (metres): it converts
    baselines to ratios and places the grid whose overlap is measured. Cameras may have any
    resolution (only their field of view matters). A candidate without baseline (e.g. the
    reference's own view in a window) is never picked.
    """
    rule = rule or SelectionRule()
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k: expected a positive integer, got {k!r}")
    if not (isinstance(depth, (int, float)) and math.isfinite(depth) and depth > 0):
        raise ValueError(f"depth: expected a positive number, got {depth!r}")
    eligible, fallback = [], []
    centres = [c.c2w64()[:3, 3] for c in candidates]
    for i, cam in enumerate(candidates):
        ratio, angle, overlap = _pair_geometry(reference, cam, depth)
        if overlap < rule.min_overlap or angle > rule.max_angle_deg or ratio <= 1e-6:
            continue
        score = overlap * math.exp(-0.5 * (math.log(ratio / rule.target_ratio) / 0.5) ** 2)
        (eligible if rule.min_ratio <= ratio <= rule.max_ratio else fallback).append((score, i))
    picked: list[int] = []

    def adjusted(i: int, pool: dict[int, float]) -> float:  # lowered next to an earlier pick
        if not picked:
            return pool[i]
        gap = min(float(np.linalg.norm(centres[i] - centres[p])) for p in picked)
        return pool[i] * min(1.0, gap / (rule.target_ratio * depth))

    for group in (eligible, fallback):  # the eligible first; the fallback only fills what they leave
        pool = {i: s for s, i in group}
        while pool and len(picked) < k:
            best = max(pool, key=lambda i: (adjusted(i, pool), -i))
            picked.append(best)
            del pool[best]
    return picked


class SourceWindow:
    """A bounded window of recent `SourceView`s (camera + matching features; never images).

    Args:
        capacity: most views kept.
        scale: sweep resolution of the views it makes from frames.
        rule: the `SelectionRule` used by `select` and by eviction.
        default_depth: the scene depth assumed while no view knows one (metres).

    ``add`` appends the newest view; when over capacity it evicts, among the older views, first the
    oldest one out of reach of the newest (no overlap, angle or baseline ratio beyond the rule's
    limits: it cannot serve the next frames), else the most redundant one (the smallest distance to
    another kept view; ties: the older). So a slowly moving camera keeps views spread over a useful
    range of baselines instead of its last few, nearly identical, frames.

    Memory: h * w * L bytes per view at sweep resolution; ``nbytes`` tells.

    A session uses it as: ``view = window.view_of(frame)``; ``sources = window.select(view, k)``;
    if ``sources`` is empty (the first frame), keep the frame pending and ``window.add(view)``; else
    ``estimate_depth(frame, sources, reference=view, ...)`` and ``window.add(view, depth=estimated)``,
    then estimate the pending frame against ``window.select(pending_view)`` (`eval.mvs_eval.stream_depth`
    does exactly this).
    """

    def __init__(self, capacity: int = 4, scale: float = DEFAULT_SCALE, rule: SelectionRule | None = None,
                 default_depth: float = 1.0):
        if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) or capacity < 1:
            raise ValueError(f"capacity: expected a positive integer, got {capacity!r}")
        if not (isinstance(scale, (int, float)) and 0 < scale <= 1):
            raise ValueError(f"scale: expected a number in (0, 1], got {scale!r}")
        if not (isinstance(default_depth, (int, float)) and math.isfinite(default_depth) and default_depth > 0):
            raise ValueError(f"default_depth: expected a positive number, got {default_depth!r}")
        self.capacity = int(capacity)
        self.scale = float(scale)
        self.rule = rule or SelectionRule()
        self.default_depth = float(default_depth)
        self.views: list[SourceView] = []

    def __len__(self) -> int:
        return len(self.views)

    def __iter__(self):
        return iter(self.views)

    @property
    def nbytes(self) -> int:
        return sum(v.nbytes for v in self.views)

    def typical_depth(self) -> float:
        """Median of the views' known typical depths, else ``default_depth`` (metres)."""
        z = _typical_depth(self.views)
        return self.default_depth if z is None else z

    def view_of(self, frame: Frame, depth=None) -> SourceView:
        """The `SourceView` of ``frame`` at this window's scale (not added)."""
        return SourceView.from_frame(frame, self.scale, depth)

    def add(self, item: Frame | SourceView, depth=None) -> SourceView:
        """Append a frame (its view is computed) or a view; ``depth`` (a depth map or a number, e.g.
        the estimated depth) sets the view's typical depth. Returns the view that was added."""
        view = item if isinstance(item, SourceView) else _as_view(item, self.scale, "frame")
        if depth is not None:
            view = replace(view, median_depth=_median_depth(depth))
        self.views.append(view)
        while len(self.views) > self.capacity:
            del self.views[self._eviction_index()]
        return view

    def _eviction_index(self) -> int:
        newest = self.views[-1].camera
        depth = self.typical_depth()
        older = self.views[:-1]
        for i, v in enumerate(older):
            ratio, angle, overlap = _pair_geometry(newest, v.camera, depth)
            if overlap < self.rule.min_overlap or angle > self.rule.max_angle_deg or ratio > self.rule.max_ratio:
                return i
        centres = [v.camera.c2w64()[:3, 3] for v in self.views]
        gaps = [min(float(np.linalg.norm(centres[i] - centres[j])) for j in range(len(centres)) if j != i)
                for i in range(len(older))]
        return int(np.argmin(gaps))  # argmin returns the first (oldest) of ties

    def select(self, item: Frame | SourceView | Camera, k: int = 2, depth: float | None = None) -> list[SourceView]:
        """Up to ``k`` views to sweep ``item`` against (see `select_sources`), best first."""
        if isinstance(item, SourceView):
            cam = item.camera
        elif isinstance(item, Frame):
            cam = item.camera
        elif isinstance(item, Camera):
            cam = item
        else:
            raise ValueError(f"item: expected a Frame, SourceView or Camera, got {type(item).__name__}")
        z = float(depth) if depth is not None else self.typical_depth()
        idx = select_sources(cam, [v.camera for v in self.views], k=k, depth=z, rule=self.rule)
        return [self.views[i] for i in idx]

    # -- snapshot -----------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain numpy arrays (for an npz) from which `from_arrays` rebuilds an identical window."""
        n = len(self.views)
        return {
            "version": np.array(1, np.int64),
            "capacity": np.array(self.capacity, np.int64),
            "scale": np.array(self.scale, np.float64),
            "default_depth": np.array(self.default_depth, np.float64),
            "rule": self.rule.as_array(),
            "K": np.array([v.camera.K64() for v in self.views], np.float64).reshape(n, 3, 3),
            "c2w": np.array([v.camera.c2w64() for v in self.views], np.float64).reshape(n, 4, 4),
            "shape": np.array([v.features.shape for v in self.views], np.int64).reshape(n, 3),
            "view_scale": np.array([v.scale for v in self.views], np.float64),
            "median_depth": np.array([v.median_depth for v in self.views], np.float64),
            "frame_id": np.array(["" if v.frame_id is None else v.frame_id for v in self.views], dtype=np.str_),
            "has_frame_id": np.array([v.frame_id is not None for v in self.views], np.bool_),
            "features": (np.concatenate([v.features.ravel() for v in self.views]) if n else np.zeros(0, np.int8)),
        }

    @classmethod
    def from_arrays(cls, d: Mapping[str, np.ndarray]) -> "SourceWindow":
        """Rebuild a window written by `to_arrays` (accepts an open ``np.load`` file too)."""
        try:
            version = int(d["version"])
            if version != 1:
                raise ValueError(f"version: unsupported source-window format {version}")
            win = cls(int(d["capacity"]), float(d["scale"]), SelectionRule.from_array(d["rule"]),
                      float(d["default_depth"]))
            shapes = np.asarray(d["shape"], np.int64).reshape(-1, 3)
            feats = np.asarray(d["features"])
            if feats.dtype != np.int8 or feats.size != int(np.prod(shapes, axis=1).sum()):
                raise ValueError(f"features: expected {int(np.prod(shapes, axis=1).sum())} int8 values, got "
                                 f"{feats.size} {feats.dtype}")
            K, c2w = np.asarray(d["K"]), np.asarray(d["c2w"])
            ids, has_id = np.asarray(d["frame_id"]), np.asarray(d["has_frame_id"])
            med, vscale = np.asarray(d["median_depth"], np.float64), np.asarray(d["view_scale"], np.float64)
        except KeyError as exc:
            raise ValueError(f"{exc.args[0]}: missing from the source-window arrays") from None
        offset = 0
        for i, (h, w, L) in enumerate(shapes):
            size = int(h * w * L)
            cam = Camera(K[i], c2w[i], int(w), int(h))
            win.views.append(SourceView(camera=cam, features=feats[offset: offset + size].reshape(h, w, L).copy(),
                                        frame_id=str(ids[i]) if has_id[i] else None,
                                        median_depth=float(med[i]), scale=float(vscale[i])))
            offset += size
        if len(win.views) > win.capacity:
            raise ValueError(f"capacity: {len(win.views)} views exceed the capacity {win.capacity}")
        return win
