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

Two implementations of the sweep: `plane_sweep` (numba, parallel over rows; integer dot products
of the int8 features, bilinear weights in float64) and `plane_sweep_reference` (pure PyTorch,
float64, for small images), held to each other by the tests. Source frames are chosen and kept by
`SourceWindow` (a bounded window of `SourceView`s: camera + matching features, no images), see
`select_sources` for the rule.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol, runtime_checkable

import numba
import numpy as np
import torch
from torch import Tensor, nn

from ..camera import Camera
from ..frame import Frame
from .matching import MATCHING_SCALE, dequantize, matching_features, sweep_luminance

DEFAULT_SCALE = 0.5
DEFAULT_NUM_HYPOTHESES = 64
EDGE_RELATIVE_JUMP = 0.05  # upsampling: sweep pixels whose depths differ more are not interpolated
MIN_SOURCE_Z = 1e-6  # a projected hypothesis must lie in front of the source camera


# ---------------------------------------------------------------------------------------------
# Source views
# ---------------------------------------------------------------------------------------------
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


def _on_image(camera: Camera, uv: Tensor, z: Tensor) -> Tensor:  # `Camera.project`'s [N, 2], [N] -> [N] bool
    """Projections in front of ``camera`` that land on its image."""
    u, v = uv[:, 0], uv[:, 1]
    return (z > 1e-9) & (u >= -0.5) & (u <= camera.width - 0.5) & (v >= -0.5) & (v <= camera.height - 0.5)


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
# Plane sweep: numba fast path and PyTorch reference
# ---------------------------------------------------------------------------------------------
def _source_transform(reference: Camera, source: Camera) -> tuple[np.ndarray, np.ndarray]:
    """A, b with K_j X_j = d * A [u, v, 1] + b for a reference pixel lifted to z-depth d."""
    rel = np.linalg.inv(source.c2w64()) @ reference.c2w64()
    Kr_inv = np.linalg.inv(reference.K64())
    Ks = source.K64()
    return np.ascontiguousarray(Ks @ rel[:3, :3] @ Kr_inv), np.ascontiguousarray(Ks @ rel[:3, 3])


@numba.njit(inline="always")
def _tap_dot(ref, src, v, u, yy, xx, cache_y, cache_x, cache_d, slot):
    # <q_ref(v, u), q_src(yy, xx)> in integers, remembered for the last few source pixels: successive
    # hypotheses walk along the epipolar line less than a pixel apart and share most of their taps
    for e in range(cache_y.shape[0]):
        if cache_y[e] == yy and cache_x[e] == xx:
            return cache_d[e], slot
    d = 0
    for c in range(ref.shape[2]):
        d += np.int32(ref[v, u, c]) * np.int32(src[yy, xx, c])
    cache_y[slot] = yy
    cache_x[slot] = xx
    cache_d[slot] = d
    return d, (slot + 1) % cache_y.shape[0]


@numba.njit(parallel=True, cache=True)
def _sweep_source_kernel(ref, src, A, b, hyps, min_z, mask, dots, count):
    # dots[v, u, k] += <q_ref(v, u), bilinear q_src at the projection of hypothesis k> (raw int8 units),
    # at the pixels where mask[v, u]
    h, w, L = ref.shape
    hs, ws = src.shape[0], src.shape[1]
    K = hyps.shape[0]
    for v in numba.prange(h):
        cache_y = np.empty(8, np.int64)
        cache_x = np.empty(8, np.int64)
        cache_d = np.empty(8, np.int64)
        for u in range(w):
            if not mask[v, u]:
                continue
            cache_y[:] = -1
            slot = 0
            a0 = A[0, 0] * u + A[0, 1] * v + A[0, 2]
            a1 = A[1, 0] * u + A[1, 1] * v + A[1, 2]
            a2 = A[2, 0] * u + A[2, 1] * v + A[2, 2]
            for k in range(K):
                d = hyps[k]
                qz = d * a2 + b[2]
                if not qz > min_z:
                    continue
                x = (d * a0 + b[0]) / qz
                y = (d * a1 + b[1]) / qz
                if not (x >= 0.0 and y >= 0.0 and x <= ws - 1 and y <= hs - 1):
                    continue
                x0 = min(int(x), ws - 2)
                y0 = min(int(y), hs - 2)
                fx = x - x0
                fy = y - y0
                d00, slot = _tap_dot(ref, src, v, u, y0, x0, cache_y, cache_x, cache_d, slot)
                d01, slot = _tap_dot(ref, src, v, u, y0, x0 + 1, cache_y, cache_x, cache_d, slot)
                d10, slot = _tap_dot(ref, src, v, u, y0 + 1, x0, cache_y, cache_x, cache_d, slot)
                d11, slot = _tap_dot(ref, src, v, u, y0 + 1, x0 + 1, cache_y, cache_x, cache_d, slot)
                s = (1.0 - fy) * ((1.0 - fx) * d00 + fx * d01) + fy * ((1.0 - fx) * d10 + fx * d11)
                dots[v, u, k] += s
                count[v, u, k] += 1


@numba.njit(parallel=True, cache=True)
def _logits_kernel(dots, count, score_scale, logits):
    h, w, K = dots.shape
    for v in numba.prange(h):
        for u in range(w):
            for k in range(K):
                n = count[v, u, k]
                logits[v, u, k] = np.float32(score_scale * dots[v, u, k] / n) if n > 0 else np.float32(0.0)


def plane_sweep(
    reference: SourceView,
    sources: Sequence[SourceView],
    hypotheses: np.ndarray,  # [K] depths (metres)
    mask: np.ndarray | None = None,  # [h, w] bool: the pixels to sweep (None = all)
) -> tuple[np.ndarray, np.ndarray]:  # logits [h, w, K] float32, seen-count [h, w, K] uint8
    """The cost volume S_k(m) (fast path): mean over seeing sources of <F_i, F_j> / sqrt(L); 0 where
    no source sees a hypothesis. Also returns how many sources see each (pixel, hypothesis).
    Pixels outside ``mask`` are not swept: no source sees them (count 0, logits 0)."""
    ref = reference.features
    h, w, L = ref.shape
    hyps = np.ascontiguousarray(hypotheses, dtype=np.float64)
    if len(sources) > 255:
        raise ValueError(f"sources: at most 255 views, got {len(sources)}")
    mask = _sweep_mask_or_all(mask, (h, w))
    dots = np.zeros((h, w, hyps.shape[0]), np.float64)
    count = np.zeros((h, w, hyps.shape[0]), np.uint8)
    for j, src in enumerate(sources):
        if src.features.shape[2] != L:
            raise ValueError(f"sources[{j}]: {src.features.shape[2]} feature channels, the reference has {L}")
        A, b = _source_transform(reference.camera, src.camera)
        _sweep_source_kernel(ref, src.features, A, b, hyps, MIN_SOURCE_Z, mask, dots, count)
    logits = np.empty((h, w, hyps.shape[0]), np.float32)
    _logits_kernel(dots, count, MATCHING_SCALE**2 / math.sqrt(L), logits)
    return logits, count


def plane_sweep_reference(
    reference: SourceView,
    sources: Sequence[SourceView],
    hypotheses: np.ndarray,  # [K]
) -> tuple[Tensor, Tensor]:  # logits [K, h, w] float64, seen-count [K, h, w] int64
    """Pure-PyTorch definition of `plane_sweep` (float64, dense; for small images and tests)."""
    Fi = dequantize(reference.features).double()  # [h, w, L]
    h, w, L = Fi.shape
    hyps = torch.as_tensor(np.asarray(hypotheses, dtype=np.float64))
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1)  # [h, w, 3]
    total = torch.zeros(len(hyps), h, w, dtype=torch.float64)
    count = torch.zeros(len(hyps), h, w, dtype=torch.int64)
    for src in sources:
        Fj = dequantize(src.features).double()  # [hs, ws, L]
        hs, ws = Fj.shape[:2]
        A, b = (torch.from_numpy(x) for x in _source_transform(reference.camera, src.camera))
        q = hyps[:, None, None, None] * (pix @ A.T)[None] + b  # [K, h, w, 3]
        z = q[..., 2]
        front = z > MIN_SOURCE_Z
        zs = torch.where(front, z, torch.ones_like(z))
        x, y = q[..., 0] / zs, q[..., 1] / zs
        seen = front & (x >= 0) & (y >= 0) & (x <= ws - 1) & (y <= hs - 1)
        x = torch.where(seen, x, torch.zeros_like(x))
        y = torch.where(seen, y, torch.zeros_like(y))
        x0 = x.floor().long().clamp(max=ws - 2)
        y0 = y.floor().long().clamp(max=hs - 2)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        sample = ((1 - fy) * ((1 - fx) * Fj[y0, x0] + fx * Fj[y0, x0 + 1])
                  + fy * ((1 - fx) * Fj[y0 + 1, x0] + fx * Fj[y0 + 1, x0 + 1]))  # [K, h, w, L]
        score = (sample * Fi[None]).sum(-1) / math.sqrt(L)
        total += torch.where(seen, score, torch.zeros_like(score))
        count += seen.long()
    logits = torch.where(count > 0, total / count.clamp(min=1), torch.zeros_like(total))
    return logits, count


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


class LogitScale(nn.Module):
    """The smallest learnable refinement: one temperature, logits * exp(log_scale).

    Starts at ``scale`` (1 = identity). Scaling the logits by s is the same as multiplying
    `matching.MATCH_SHARPNESS` by s, so this is also how to try another sharpness without
    recomputing features (bench/depth.py does).
    """

    def __init__(self, scale: float = 1.0):
        super().__init__()
        if not (isinstance(scale, (int, float)) and scale > 0):
            raise ValueError(f"scale: expected a positive number, got {scale!r}")
        self.log_scale = nn.Parameter(torch.tensor(math.log(scale), dtype=torch.float64))

    def forward(self, logits: Tensor, hypotheses: Tensor, features: Tensor | None = None) -> Tensor:
        return logits * self.log_scale.exp().to(logits.dtype)


# ---------------------------------------------------------------------------------------------
# Cost volume -> depth distribution
# ---------------------------------------------------------------------------------------------
@numba.njit(parallel=True, cache=True)
def _distribution_kernel(logits, count, hyps, mask, depth, unc, seen_mass, valid):
    h, w, K = logits.shape
    for v in numba.prange(h):
        p = np.empty(K)  # the pixel's unnormalised probabilities, reused by the second pass
        for u in range(w):
            if not mask[v, u]:  # not swept: no source saw it
                depth[v, u] = 0.0
                unc[v, u] = 0.0
                seen_mass[v, u] = 0.0
                valid[v, u] = False
                continue
            m = logits[v, u, 0]
            for k in range(1, K):
                m = max(m, logits[v, u, k])
            z = 0.0
            s1 = 0.0
            vis = 0.0
            for k in range(K):
                p[k] = math.exp(np.float64(logits[v, u, k]) - m)
                z += p[k]
                s1 += p[k] * hyps[k]
                if count[v, u, k] > 0:
                    vis += p[k]
            mean = s1 / z
            s2 = 0.0
            best = 0
            best_gap = 1e300
            for k in range(K):
                s2 += p[k] * (hyps[k] - mean) ** 2
                gap = abs(1.0 / hyps[k] - 1.0 / mean)
                if gap < best_gap:
                    best_gap = gap
                    best = k
            depth[v, u] = mean
            unc[v, u] = math.sqrt(s2 / z)
            seen_mass[v, u] = vis / z
            valid[v, u] = (vis / z >= 0.5) and count[v, u, best] > 0


def depth_distribution(
    logits: np.ndarray,  # [h, w, K] float32
    count: np.ndarray,  # [h, w, K] sources seeing each hypothesis
    hypotheses: np.ndarray,  # [K]
    mask: np.ndarray | None = None,  # [h, w] bool: the swept pixels (None = all); elsewhere 0 and invalid
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # D, U_pos [h, w] float64, seen mass, valid
    """P = softmax over hypotheses; D = sum P d; U_pos = sqrt(sum P (d - D)^2) (numba fast path)."""
    h, w, K = logits.shape
    depth, unc, mass = (np.empty((h, w), np.float64) for _ in range(3))
    valid = np.empty((h, w), np.bool_)
    _distribution_kernel(np.ascontiguousarray(logits, dtype=np.float32), np.ascontiguousarray(count),
                         np.ascontiguousarray(hypotheses, dtype=np.float64), _sweep_mask_or_all(mask, (h, w)),
                         depth, unc, mass, valid)
    return depth, unc, mass, valid


def depth_distribution_reference(
    logits: Tensor,  # [B, K, h, w] (after refinement)
    count: Tensor,  # [B, K, h, w]
    hypotheses: Tensor,  # [K]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:  # D, U_pos, seen mass, valid: [B, h, w]
    """Differentiable PyTorch definition of `depth_distribution` (use it to train a refinement)."""
    P = torch.softmax(logits, dim=1)
    d = hypotheses.to(P.dtype).view(1, -1, 1, 1)
    D = (P * d).sum(1)
    U = (P * (d - D[:, None]).square()).sum(1).clamp_min(0).sqrt()
    mass = (P * (count > 0).to(P.dtype)).sum(1)
    nearest = (1.0 / d - 1.0 / D[:, None]).abs().argmin(1, keepdim=True)
    seen_at_D = torch.gather(count, 1, nearest)[:, 0] > 0
    return D, U, mass, (mass >= 0.5) & seen_at_D


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


def _sweep_mask_or_all(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, np.bool_)
    if not isinstance(mask, np.ndarray) or mask.shape != shape:
        raise ValueError(f"mask: expected a bool array of shape {list(shape)} (the sweep resolution), got "
                         f"{list(getattr(mask, 'shape', []))}")
    return np.ascontiguousarray(mask, dtype=np.bool_)


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


def _typical_depth(views: Sequence[SourceView]) -> float | None:
    """Median of the views' known typical depths (metres), None when none knows one."""
    known = [v.median_depth for v in views if math.isfinite(v.median_depth)]
    return float(np.median(known)) if known else None


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


def sensor_holes(
    depth: np.ndarray,  # [H, W] float32 sensor depth, 0 = missing
    radius: int,
) -> np.ndarray:  # [H, W] bool
    """The pixels with no measured depth within ``radius`` pixels (a square window): the regions a
    depth sensor does not reach (beyond its range, outside its field of view, dark or specular
    surfaces), not the small regular holes of its pattern, which voxels bridge anyway.

    Example:
        >>> d = np.zeros((3, 8), np.float32); d[:, :2] = 1.0
        >>> sensor_holes(d, radius=2)[0].astype(int).tolist()
        [0, 0, 0, 0, 1, 1, 1, 1]
    """
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 1:
        raise ValueError(f"radius: expected a positive integer, got {radius!r}")
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise ValueError(f"depth: expected an [H, W] array, got {list(getattr(depth, 'shape', []))}")
    measured = (depth > 0).astype(np.int32)
    return _window_sum(_window_sum(measured, radius, 0), radius, 1) == 0


def _window_sum(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """Sums of ``a`` over windows [i - radius, i + radius] along ``axis`` (clipped at the borders),
    from one cumulative sum: the cost does not grow with the radius."""
    n = a.shape[axis]
    c = np.cumsum(a, axis=axis, dtype=np.int32)  # counts of at most H * W pixels
    c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
    i = np.arange(n)
    return np.take(c, np.minimum(i + radius + 1, n), axis=axis) - np.take(c, np.maximum(i - radius, 0), axis=axis)


def complete_depth(
    depth: np.ndarray,  # [H, W] float32 sensor depth, metres, 0 = missing
    depth_std: np.ndarray,  # [H, W] float32 the sensor depth's std, metres
    estimate: np.ndarray,  # [H, W] float32 swept depth (`estimate_depth`), 0 = none
    uncertainty: np.ndarray,  # [H, W] float32 its U_pos, metres
    holes: np.ndarray,  # [H, W] bool: the pixels to fill (`sensor_holes`)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # depth [H, W], std [H, W] float32, filled [H, W] bool
    """Sensor depth with its large holes filled from the plane sweep.

    A pixel is filled when it is one of ``holes`` and the sweep gives it a depth. Filled pixels carry
    the sweep's U_pos as their std, so their reliability is as low as the sweep is unsure; sensor
    pixels are never changed. Sweep depth is a few voxels off where sensor depth is within one, so
    where earlier frames measured the same surface the fill adds a less exact copy of it (depth
    agreement falls a little). Only the holes need a sweep: ``estimate_depth(..., where=holes)``.

    Example:
        >>> d = np.zeros((5, 9), np.float32); d[:, :3] = 1.0
        >>> est = np.full((5, 9), 2.0, np.float32)
        >>> out, std, filled = complete_depth(d, np.full_like(d, 0.01), est, np.full_like(d, 0.1), sensor_holes(d, 2))
        >>> filled[0].astype(int).tolist(), out[0].tolist()
        ([0, 0, 0, 0, 0, 1, 1, 1, 1], [1.0, 1.0, 1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 2.0])
    """
    shape = depth.shape
    for name, value in (("depth_std", depth_std), ("estimate", estimate), ("uncertainty", uncertainty), ("holes", holes)):
        if value.shape != shape:
            raise ValueError(f"{name}: expected shape {list(shape)} (as depth), got {list(value.shape)}")
    if holes.dtype != np.bool_:
        raise ValueError(f"holes: expected a bool array, got {holes.dtype}")
    filled = holes & (depth <= 0) & (estimate > 0)
    out = np.where(filled, estimate, depth).astype(np.float32)
    std = np.where(filled, uncertainty, depth_std).astype(np.float32)
    return out, std, filled


# ---------------------------------------------------------------------------------------------
# Choosing and keeping source views
# ---------------------------------------------------------------------------------------------
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
    beats none, and where the depth stays uncertain U_pos says so. On the shelf streamed as its 8
    evaluation inputs (8 degrees apart, 640x480), filling the second source lowered the median
    AbsRel from 0.053 to 0.049 and raised RGB-only fusion by 0.33 dB (`bench/rgb_only.py`).

    The defaults come from the shelf capture (4 frames, one source on each side 6 / 8 / 10 frames
    away, baseline ratio ~0.14 / 0.19 / 0.24: median AbsRel 0.058 / 0.052 / 0.076; 4 frames away,
    ~0.1: 0.07). Wider baselines change the appearance too much, narrower ones do not separate
    the hypotheses; in a stream, target ratios 0.12-0.2 and window capacities 4-6 gave the same
    median AbsRel within 0.001.
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

    Memory: h * w * L bytes per view (640x480 frames at scale 0.5: 7.7 MB); ``nbytes`` tells.

    A session uses it as: ``view = window.view_of(frame)``; ``sources = window.select(view, k)``;
    if ``sources`` is empty (the first frame), keep the frame pending and ``window.add(view)``; else
    ``estimate_depth(frame, sources, reference=view, ...)`` and ``window.add(view, depth=estimated)``,
    then estimate the pending frame against ``window.select(pending_view)`` (`mvs_eval.stream_depth`
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
