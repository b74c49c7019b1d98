"""Multi-view depth for frames without depth: plane sweep with positional uncertainty (Ext, 2.5D).

The paper's rule, as implemented here (reference frame i, sources j, pixel m at sweep resolution):

    d_k      K hypotheses, uniform in inverse depth between near and far          (`depth_hypotheses`)
    m_k^j    m lifted to depth d_k in view i and projected into source j
    S_k(m) = mean over the sources j that see m_k^j of <F_i(m), F_j(m_k^j)> / sqrt(L)
             (F_j bilinearly interpolated; a hypothesis no source sees scores 0, i.e. "no evidence")
    P      = softmax_k(refine(S))                  (refine: `DepthRefinement`, identity by default)
    D(m)   = sum_k P_k d_k,  U_pos(m) = sqrt(sum_k P_k (d_k - D(m))^2)   (metres)

F are the matching features of `matching.py` (multi-scale band-limited NCC patches, scaled so that
the softmax is peaked enough; their L differs from the fused F_view's). A pixel gets a depth only if
it is seen: the probability mass of the hypotheses seen by at least one source is >= 0.5 *and* the
hypothesis nearest to D is seen; every other pixel gets depth 0 (missing), never a guess.
The sweep runs at ``scale`` x the image resolution; D and U_pos are then upsampled to the image:
bilinearly where the four surrounding sweep pixels are valid and agree (depth spread <= 5 % of the
nearest), from the nearest sweep pixel across depth edges (no interpolated "flying" depths); U_pos
is the spread of the upsampled (bilinearly mixed) distribution about that depth (`upsample_depth`).

Reliability follows exactly as with supplied depth: pass ``depth_std=uncertainty`` (metres) to
`reliability.positional_uncertainty`, which converts it to voxel units and adds the depth-edge term.

This module chooses the swept range and hypotheses, runs the sweep (`sweep`: the cost volume and
its distribution, each with a PyTorch reference), applies a refinement if given and upsamples the
result. Source views are chosen and kept by `source_views` (`select_sources`, `SourceWindow`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor, nn

from ..camera import Camera
from ..frame import Frame
from .matching import dequantize
from .source_views import DEFAULT_SCALE, SourceView, _as_view, _on_image, _typical_depth
from .sweep import depth_distribution, depth_distribution_reference, plane_sweep

DEFAULT_NUM_HYPOTHESES = 64
EDGE_RELATIVE_JUMP = 0.05  # upsampling: sweep pixels whose depths differ more are not interpolated


# ---------------------------------------------------------------------------------------------
# Hypotheses and depth ranges
# ---------------------------------------------------------------------------------------------
def depth_hypotheses(near: float, far: float, num: int = DEFAULT_NUM_HYPOTHESES) -> np.ndarray:  # [K] float64
    """``num`` depths uniform in inverse depth from ``near`` to ``far`` (increasing depth)."""
    if not (isinstance(near, (int, float)) and isinstance(far, (int, float)) and math.isfinite(near)
            and math.isfinite(far) and 0 < near < far):
        raise ValueError(f"near, far: expected 0 < near < far (finite), got near={near!r}, far={far!r}")
    if isinstance(num, bool) or not isinstance(num, (int, np.integer)) or num < 2:
        raise ValueError(f"num_hypotheses: expected an integer >= 2, got {num!r}")
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, int(num))


def _range_from_values(z: np.ndarray, low: float, high: float, margin: float, min_count: int):
    if not (0 <= low < high <= 100):
        raise ValueError(f"low, high: expected percentiles 0 <= low < high <= 100, got {low!r}, {high!r}")
    if not (0 <= margin < 1):
        raise ValueError(f"margin: expected a fraction in [0, 1), got {margin!r}")
    z = z[np.isfinite(z) & (z > 0)]
    if z.size < min_count:
        return None
    lo, hi = np.percentile(z, [low, high])
    near, far = float(lo) * (1.0 - margin), float(hi) * (1.0 + margin)
    if far <= near * 1.05:  # a flat scene: keep a usable range around it
        near, far = near / 1.2, far * 1.2
    return near, far



def depth_range_from_points(
    camera: Camera,
    points,  # [N, 3] world points the scene already holds (e.g. voxel representatives)
    low: float = 2.0,
    high: float = 98.0,
    margin: float = 0.25,
    min_count: int = 50,
) -> tuple[float, float] | None:
    """(near, far) for a sweep in ``camera`` from scene points it sees: the low/high percentiles of
    their depths widened by ``margin`` (relative). None when fewer than ``min_count`` points are seen."""
    pts = torch.as_tensor(np.asarray(points, dtype=np.float32))
    if pts.ndim != 2 or pts.shape[-1] != 3:
        raise ValueError(f"points: expected [N, 3], got {list(pts.shape)}")
    if pts.shape[0] == 0:
        return None
    uv, z = camera.project(pts)
    return _range_from_values(z[_on_image(camera, uv, z)].numpy().astype(np.float64), low, high, margin, min_count)


def depth_range_from_depth(depth, low: float = 2.0, high: float = 98.0, margin: float = 0.25,
                           min_count: int = 50) -> tuple[float, float] | None:
    """(near, far) from a depth map (a previous frame's sensor or estimated depth), as above."""
    d = np.asarray(depth.numpy() if isinstance(depth, Tensor) else depth, dtype=np.float64).ravel()
    return _range_from_values(d, low, high, margin, min_count)


# ---------------------------------------------------------------------------------------------
# Learned refinement hook
# ---------------------------------------------------------------------------------------------
@runtime_checkable
class DepthRefinement(Protocol):
    """Refines the cost volume's logits before the softmax (a learned module, e.g. a 3D CNN).

    Called as ``refine(logits, hypotheses, features)`` with logits [B, K, h, w] (the scores S_k),
    hypotheses [K] (metres) and the reference's matching features [B, L, h, w]; returns refined
    logits [B, K, h, w]. Must not change which hypotheses exist.
    """

    def __call__(self, logits: Tensor, hypotheses: Tensor, features: Tensor) -> Tensor: ...


class IdentityRefinement(nn.Module):
    """The default `DepthRefinement`: returns the logits unchanged (the training-free path)."""

    def forward(self, logits: Tensor, hypotheses: Tensor, features: Tensor | None = None) -> Tensor:
        return logits



def _is_identity(refine) -> bool:
    return refine is None or isinstance(refine, IdentityRefinement)


# ---------------------------------------------------------------------------------------------
# Upsampling to the image
# ---------------------------------------------------------------------------------------------
def _upsample_taps(n: int, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along one axis, for each of N image pixels: its position in a grid of n sweep pixels
    (pixel-centre convention) and its two bilinear taps [N] each."""
    pos = np.clip((np.arange(N) + 0.5) * (n / N) - 0.5, 0, n - 1)
    lo = np.minimum(np.floor(pos).astype(np.int64), max(n - 2, 0))
    return pos, lo, np.minimum(lo + 1, n - 1)


def sweep_pixels_for(
    where: np.ndarray,  # [H, W] bool: the image pixels whose depth is wanted
    size: tuple[int, int],  # (h, w) sweep resolution
) -> np.ndarray:  # [h, w] bool
    """The sweep pixels that `upsample_depth` reads for the image pixels ``where``: sweeping only
    these gives those pixels the same depth as a full sweep.

    Example:
        >>> where = np.zeros((4, 8), bool); where[:, :2] = True
        >>> sweep_pixels_for(where, (2, 4)).astype(int).tolist()
        [[1, 1, 0, 0], [1, 1, 0, 0]]
    """
    where = np.asarray(where, dtype=bool)
    (h, w), (H, W) = size, where.shape
    _, y0, y1 = _upsample_taps(h, H)
    _, x0, x1 = _upsample_taps(w, W)
    rows = np.zeros((h, W), bool)  # sweep row r is read by some wanted pixel of image column c
    for taps in (y0, y1):
        np.logical_or.at(rows, taps, where)
    out = np.zeros((h, w), bool)
    for taps in (x0, x1):
        np.logical_or.at(out.T, taps, rows.T)
    return out



def upsample_depth(
    depth: np.ndarray,  # [h, w] sweep-resolution depth, 0 = missing
    uncertainty: np.ndarray,  # [h, w] U_pos at sweep resolution
    size: tuple[int, int],  # (H, W)
    edge_jump: float = EDGE_RELATIVE_JUMP,
) -> tuple[np.ndarray, np.ndarray]:  # [H, W] float32 each
    """Upsample the depth distribution: each image pixel's P is the bilinear mixture of the P of the
    (valid) sweep pixels around it (pixel-centre convention).

    Depth: the mixture's mean where the four sweep pixels are valid and within ``edge_jump``
    (relative) of each other; elsewhere the nearest sweep pixel's depth (0 if it has none), so a
    depth edge never gets in-between "flying" depths. U_pos: sqrt of the mixture's second moment
    about that depth, sum_t w_t (U_t^2 + (D_t - D)^2) over the valid taps (weights renormalised):
    where the taps agree this is about the taps' U_pos; next to an edge it includes the jump,
    because that is how unsure the upsampled depth is there.
    """
    h, w = depth.shape
    ys, y0, y1 = _upsample_taps(h, size[0])
    xs, x0, x1 = _upsample_taps(w, size[1])
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    r0, r1, c0, c1 = y0[:, None], y1[:, None], x0[None, :], x1[None, :]
    taps = [(r0, c0), (r0, c1), (r1, c0), (r1, c1)]
    wts = [(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx]
    d64, u64 = depth.astype(np.float64), uncertainty.astype(np.float64)
    dt = [d64[r, c] for r, c in taps]
    ut = [u64[r, c] for r, c in taps]
    wv = [np.where(d > 0, wt, 0.0) for wt, d in zip(wts, dt)]  # weights of valid taps
    wsum = sum(wv)
    lo = np.minimum(np.minimum(dt[0], dt[1]), np.minimum(dt[2], dt[3]))
    hi = np.maximum(np.maximum(dt[0], dt[1]), np.maximum(dt[2], dt[3]))
    smooth = (lo > 0) & (hi - lo <= edge_jump * lo)
    d_mix = sum(wt * d for wt, d in zip(wv, dt)) / np.maximum(wsum, 1e-12)
    yn = np.clip(np.rint(ys).astype(np.int64), 0, h - 1)[:, None]
    xn = np.clip(np.rint(xs).astype(np.int64), 0, w - 1)[None, :]
    d_out = np.where(smooth, d_mix, d64[yn, xn])
    m2 = sum(wt * (u * u + (d - d_out) ** 2) for wt, u, d in zip(wv, ut, dt)) / np.maximum(wsum, 1e-12)
    u_out = np.where(d_out > 0, np.sqrt(m2), 0.0)
    return d_out.astype(np.float32), u_out.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Public entry point
# ---------------------------------------------------------------------------------------------
@dataclass
class DepthEstimate:
    """Everything `estimate_depth_detailed` computed.

    Attributes:
        depth, uncertainty: [H, W] float32 metres at image resolution (0 / 0 where missing).
        sweep_depth, sweep_uncertainty: [h, w] float32 at sweep resolution (0 where missing).
        seen_mass: [h, w] probability mass on hypotheses that some source sees.
        hypotheses: [K] float64 depths swept.
        reference: the reference frame's `SourceView` (add it to a `SourceWindow` to reuse it).
        sources: the source views used.
    """

    depth: np.ndarray
    uncertainty: np.ndarray
    sweep_depth: np.ndarray
    sweep_uncertainty: np.ndarray
    seen_mass: np.ndarray
    hypotheses: np.ndarray
    reference: SourceView
    sources: list = field(default_factory=list)



def _resolve_range(near, far, views: Sequence[SourceView]) -> tuple[float, float]:
    if near is None or far is None:
        z = _typical_depth(views)
        default_near, default_far = (0.4 * z, 3.0 * z) if z else (0.1, 10.0)
        if near is None:
            near = default_near if far is None else min(default_near, 0.5 * float(far))
        if far is None:
            far = max(default_far, 2.0 * float(near))
    return float(near), float(far)


def estimate_depth_detailed(
    frame: Frame,
    sources: Sequence[Frame | SourceView],
    near: float | None = None,
    far: float | None = None,
    num_hypotheses: int = DEFAULT_NUM_HYPOTHESES,
    scale: float = DEFAULT_SCALE,
    refine: DepthRefinement | None = None,
    reference: SourceView | None = None,
    where: np.ndarray | None = None,
) -> DepthEstimate:
    """`estimate_depth` with its intermediate results (see `DepthEstimate`)."""
    if not isinstance(frame, Frame):
        raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
    if isinstance(sources, (Frame, SourceView)) or not isinstance(sources, Sequence):
        raise ValueError("sources: expected a sequence of Frame or SourceView")
    if len(sources) == 0:
        raise ValueError("sources: empty; a frame without depth needs at least one source view")
    ref = reference if reference is not None else SourceView.from_frame(frame, scale)
    if not isinstance(ref, SourceView):
        raise ValueError(f"reference: expected a SourceView, got {type(ref).__name__}")
    views = [_as_view(s, ref.scale, f"sources[{i}]") for i, s in enumerate(sources)]
    near, far = _resolve_range(near, far, views)
    hyps = depth_hypotheses(near, far, num_hypotheses)
    mask = None
    if where is not None:
        if not isinstance(where, np.ndarray) or where.dtype != np.bool_ or where.shape != (frame.height, frame.width):
            raise ValueError(f"where: expected a bool array of shape {[frame.height, frame.width]} (the image), got "
                             f"{getattr(where, 'dtype', type(where).__name__)} {list(getattr(where, 'shape', []))}")
        mask = sweep_pixels_for(where, ref.features.shape[:2])
    logits, count = plane_sweep(ref, views, hyps, mask)
    if _is_identity(refine):
        D, U, mass, valid = depth_distribution(logits, count, hyps, mask)
    else:
        lt = torch.from_numpy(logits).permute(2, 0, 1)[None]
        feats = dequantize(ref.features).permute(2, 0, 1)[None]
        ht = torch.from_numpy(hyps)
        with torch.no_grad():
            lt = refine(lt, ht.to(lt.dtype), feats)
        if tuple(lt.shape) != (1, len(hyps)) + logits.shape[:2]:
            raise ValueError(f"refine: returned shape {list(lt.shape)}, expected {[1, len(hyps), *logits.shape[:2]]}")
        ct = torch.from_numpy(count.astype(np.int64)).permute(2, 0, 1)[None]
        Dt, Ut, mt, vt = depth_distribution_reference(lt.double(), ct, ht)
        D, U, mass, valid = Dt[0].numpy(), Ut[0].numpy(), mt[0].numpy(), vt[0].numpy()
    sweep_depth = np.where(valid, D, 0.0).astype(np.float32)
    sweep_unc = np.where(valid, U, 0.0).astype(np.float32)
    depth, unc = upsample_depth(sweep_depth, sweep_unc, (frame.height, frame.width))
    return DepthEstimate(depth=depth, uncertainty=unc, sweep_depth=sweep_depth, sweep_uncertainty=sweep_unc,
                         seen_mass=mass.astype(np.float32), hypotheses=hyps, reference=ref, sources=views)


def estimate_depth(
    frame: Frame,
    sources: Sequence[Frame | SourceView],
    near: float | None = None,
    far: float | None = None,
    num_hypotheses: int = DEFAULT_NUM_HYPOTHESES,
    scale: float = DEFAULT_SCALE,
    refine: DepthRefinement | None = None,
    reference: SourceView | None = None,
    where: np.ndarray | None = None,  # [H, W] bool: the pixels whose depth is wanted (None = all)
) -> tuple[np.ndarray, np.ndarray]:  # depth [H, W] float32 metres (0 = missing), U_pos [H, W] float32 metres
    """Depth of ``frame`` from its ``sources`` by plane sweep, and its positional uncertainty.

    Args:
        frame: the reference frame (its own depth, if any, is ignored).
        sources: other views of the scene: Frames (depth not needed) or `SourceView`s, e.g. from
            `SourceWindow.select`.
        near, far: the swept depth range (metres): the session's settings, or derived from what the
            scene holds (`depth_range_from_points`). When left out: 0.4x to 3x the sources' typical
            depth if they know it, else 0.1 to 10 (coarse: pass a range).
        num_hypotheses: K.
        scale: sweep resolution relative to the image (the result is upsampled to the image).
        refine: a `DepthRefinement` applied to the logits before the softmax (None = identity).
        reference: the frame's precomputed `SourceView` (same ``scale``), to avoid recomputing it.
        where: the image pixels whose depth is wanted. Only the sweep pixels their upsampling reads
            are swept (`sweep_pixels_for`), so these pixels get the depth of a full sweep at a
            fraction of its cost; other pixels may get none. A refinement that looks at
            neighbouring pixels sees unswept ones as flat (all logits 0).

    Returns (depth, uncertainty), both [H, W] float32 in metres; 0 (and 0) where no source sees the
    pixel. ``uncertainty`` is U_pos = sqrt(sum_k P_k (d_k - D)^2).

    Example:
        >>> from canonical_core.datasets import synthetic_rgbd
        >>> seq = synthetic_rgbd(num_frames=3, width=64, height=48)
        >>> depth, unc = estimate_depth(seq[1], [seq[0], seq[2]], near=0.5, far=5.0, num_hypotheses=16)
        >>> depth.shape, unc.dtype.name
        ((48, 64), 'float32')
    """
    est = estimate_depth_detailed(frame, sources, near, far, num_hypotheses, scale, refine, reference, where)
    return est.depth, est.uncertainty
