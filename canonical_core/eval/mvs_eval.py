"""Measuring multi-view depth against sensor depth: protocols and uncertainty metrics.

Two protocols, both with the sensor depth withheld from the estimator (it is only the ground truth):

- `stream_depth`: what a session does. Frames arrive in order; each one is swept against up to
  ``num_sources`` views chosen by a `SourceWindow` of past frames; its estimated depth sets the
  view's typical depth; the first frame waits for a partner and is then estimated.
- `offline_depth`: every reference frame may use any other frame of the capture (chosen by
  `select_sources`), e.g. to measure the estimator itself with 1, 2, 4 sources.

Metrics: AbsRel = |D - D_gt| / D_gt on pixels with sensor depth and an estimate; the sparsification
curve (error of the pixels kept after dropping the most uncertain fraction first), its oracle
(dropping the largest errors first) and AUSE, the area between them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from ..evidence.mvs import DEFAULT_NUM_HYPOTHESES, DepthEstimate, estimate_depth_detailed
from ..evidence.source_views import DEFAULT_SCALE, SelectionRule, SourceView, SourceWindow, select_sources
from ..frame import Frame


class LogitScale(nn.Module):
    """The smallest learnable depth refinement (a `evidence.mvs.DepthRefinement`): one temperature,
    logits * exp(log_scale).

    Starts at ``scale`` (1 = identity). Scaling the logits by s is the same as multiplying
    `matching.MATCH_SHARPNESS` by s, so this is also how to try another sharpness without
    recomputing features.
    """

    def __init__(self, scale: float = 1.0):
        super().__init__()
        if not (isinstance(scale, (int, float)) and scale > 0):
            raise ValueError(f"scale: expected a positive number, got {scale!r}")
        self.log_scale = nn.Parameter(torch.tensor(math.log(scale), dtype=torch.float64))

    def forward(self, logits: Tensor, hypotheses: Tensor, features: Tensor | None = None) -> Tensor:
        return logits * self.log_scale.exp().to(logits.dtype)


def without_depth(frame: Frame) -> Frame:
    """The frame as an RGB-only camera would send it."""
    return dataclasses.replace(frame, depth=None, depth_std=None)


@dataclass
class FrameDepthResult:
    """One estimated frame against its sensor depth.

    Attributes:
        index, frame_id: which frame.
        sources: ids (or indices) of the source frames used.
        abs_rel, uncertainty: [M] per-pixel AbsRel and U_pos (metres) on pixels with both depths.
        coverage: share of the sensor-depth pixels that got an estimate.
        estimate: the full `DepthEstimate` (None unless kept).
    """

    index: int
    frame_id: str | None
    sources: list
    abs_rel: np.ndarray
    uncertainty: np.ndarray
    coverage: float
    estimate: DepthEstimate | None = None

    @property
    def median_abs_rel(self) -> float:
        return float(np.median(self.abs_rel)) if self.abs_rel.size else math.nan


def compare_to_sensor(
    depth: np.ndarray,  # [H, W] estimate, 0 = missing
    uncertainty: np.ndarray,  # [H, W]
    sensor: np.ndarray,  # [H, W] ground truth, 0 = missing
) -> tuple[np.ndarray, np.ndarray, float]:
    """(AbsRel [M], U_pos [M], coverage) on the pixels where the sensor has depth."""
    gt = np.asarray(sensor, np.float64)
    has_gt = np.isfinite(gt) & (gt > 0)
    both = has_gt & (depth > 0)
    coverage = float(both.sum() / max(has_gt.sum(), 1))
    abs_rel = np.abs(depth[both] - gt[both]) / gt[both]
    return abs_rel.astype(np.float64), uncertainty[both].astype(np.float64), coverage


def sparsification(
    errors: np.ndarray,  # [M] per-pixel errors
    uncertainty: np.ndarray,  # [M] per-pixel uncertainty
    steps: int = 20,
    statistic=np.mean,
) -> dict:
    """Sparsification curve, oracle and AUSE.

    Returns ``fractions`` (share removed: 0, 1/steps, ..., (steps-1)/steps), ``curve`` (statistic of
    the errors kept after removing the most uncertain first), ``oracle`` (removing the largest
    errors first), ``ause`` (trapezoidal area between curve and oracle over the fractions) and
    ``monotone`` (whether the curve never rises).
    """
    e = np.asarray(errors, np.float64)
    u = np.asarray(uncertainty, np.float64)
    if e.shape != u.shape or e.ndim != 1 or e.size == 0:
        raise ValueError(f"errors, uncertainty: expected two non-empty [M] arrays, got {e.shape} and {u.shape}")
    by_u = e[np.argsort(-u, kind="stable")]
    by_e = np.sort(e)[::-1]
    fractions = np.arange(steps) / steps
    curve, oracle = [], []
    for f in fractions:
        drop = int(round(f * e.size))
        curve.append(float(statistic(by_u[drop:])))
        oracle.append(float(statistic(by_e[drop:])))
    curve, oracle = np.array(curve), np.array(oracle)
    gap = curve - oracle
    ause = float(np.sum((gap[1:] + gap[:-1]) * 0.5 * np.diff(fractions)))
    return {"fractions": fractions, "curve": curve, "oracle": oracle, "ause": ause,
            "monotone": bool(np.all(np.diff(curve) <= 1e-12))}


def certain_half_ratio(errors: np.ndarray, uncertainty: np.ndarray) -> float:
    """Median error of the most certain 50 % of the pixels / median error of all pixels."""
    e = np.asarray(errors, np.float64)
    order = np.argsort(np.asarray(uncertainty, np.float64), kind="stable")
    return float(np.median(e[order[: max(1, e.size // 2)]]) / np.median(e))


def stream_depth(
    frames: Iterable[Frame],
    num_sources: int = 2,
    near: float = 0.2,
    far: float = 2.0,
    num_hypotheses: int = DEFAULT_NUM_HYPOTHESES,
    scale: float = DEFAULT_SCALE,
    capacity: int = 4,
    default_depth: float | None = None,
    rule: SelectionRule | None = None,
    keep_estimates: bool = False,
) -> list[FrameDepthResult]:
    """The session protocol (see the module docstring); frames with sensor depth are scored against it.

    Results are in the order frames were estimated (the first frame comes after the second).
    """
    window = SourceWindow(capacity=capacity, scale=scale, rule=rule,
                          default_depth=default_depth or math.sqrt(near * far))
    results: list[FrameDepthResult] = []
    pending: list[tuple[int, Frame, SourceView]] = []

    def run(index: int, frame: Frame, view: SourceView, sources: list[SourceView]) -> np.ndarray:  # the estimated depth
        est = estimate_depth_detailed(without_depth(frame), sources, near, far, num_hypotheses, scale, reference=view)
        if frame.depth is not None:
            abs_rel, unc, cov = compare_to_sensor(est.depth, est.uncertainty, frame.depth.numpy())
        else:
            abs_rel, unc, cov = np.zeros(0), np.zeros(0), math.nan
        results.append(FrameDepthResult(index, frame.frame_id, [s.frame_id for s in sources], abs_rel, unc, cov,
                                        est if keep_estimates else None))
        return est.depth

    for index, frame in enumerate(frames):
        view = SourceView.from_frame(without_depth(frame), scale)
        sources = window.select(view, k=num_sources)
        if not sources:
            pending.append((index, frame, view))
            window.add(view)
            continue
        window.add(view, depth=run(index, frame, view, sources))
        still = []
        for p_index, p_frame, p_view in pending:  # the first frame(s): folded once a partner exists
            p_sources = window.select(p_view, k=num_sources)  # never p_view itself (zero baseline)
            if p_sources:
                run(p_index, p_frame, p_view, p_sources)
            else:
                still.append((p_index, p_frame, p_view))
        pending = still
    return results


def offline_depth(
    frames: Sequence[Frame],
    references: Sequence[int],
    num_sources: int = 2,
    near: float = 0.2,
    far: float = 2.0,
    num_hypotheses: int = DEFAULT_NUM_HYPOTHESES,
    scale: float = DEFAULT_SCALE,
    typical_depth: float | None = None,
    rule: SelectionRule | None = None,
    keep_estimates: bool = False,
    refine=None,
) -> list[FrameDepthResult]:
    """Each reference frame swept against the best ``num_sources`` other frames of the capture."""
    depth = typical_depth or math.sqrt(near * far)
    cams = [f.camera for f in frames]
    cache: dict[int, SourceView] = {}

    def view(i: int) -> SourceView:
        if i not in cache:
            if len(cache) > 4 * (num_sources + 1):
                cache.pop(next(iter(cache)))
            cache[i] = SourceView.from_frame(without_depth(frames[i]), scale)
        return cache[i]

    results = []
    for r in references:
        others = [i for i in range(len(frames)) if i != r]
        picked = [others[j] for j in select_sources(cams[r], [cams[i] for i in others], k=num_sources,
                                                    depth=depth, rule=rule)]
        if not picked:
            continue
        frame = frames[r]
        est = estimate_depth_detailed(without_depth(frame), [view(i) for i in picked], near, far, num_hypotheses,
                                      scale, refine=refine, reference=view(r))
        abs_rel, unc, cov = compare_to_sensor(est.depth, est.uncertainty, frame.depth.numpy())
        results.append(FrameDepthResult(r, frame.frame_id, picked, abs_rel, unc, cov, est if keep_estimates else None))
    return results


def summarize(results: Sequence[FrameDepthResult]) -> dict:
    """Pooled numbers over frames: median AbsRel (pooled pixels and median of per-frame medians),
    coverage, the share within 5 %, the sparsification curve / AUSE and the certain-half ratio."""
    e = np.concatenate([r.abs_rel for r in results])
    u = np.concatenate([r.uncertainty for r in results])
    sp = sparsification(e, u)
    return {
        "frames": len(results),
        "pixels": int(e.size),
        "median_abs_rel": float(np.median(e)),
        "median_of_frame_medians": float(np.median([r.median_abs_rel for r in results])),
        "mean_abs_rel": float(e.mean()),
        "median_uncertainty": float(np.median(u)),
        "within_5pct": float((e < 0.05).mean()),
        "coverage": float(np.nanmean([r.coverage for r in results])),
        "ause": sp["ause"],
        "sparsification": sp,
        "certain_half_ratio": certain_half_ratio(e, u),
    }
