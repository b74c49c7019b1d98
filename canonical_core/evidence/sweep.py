"""The plane sweep's cost volume and its depth distribution (see `mvs` for the equations).

Two implementations of each: numba fast paths (`plane_sweep`: parallel over rows, integer dot
products of the int8 features, bilinear weights in float64; `depth_distribution`) and PyTorch
definitions (`plane_sweep_reference`: float64, dense, for small images;
`depth_distribution_reference`: differentiable), held to each other by the tests.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from .matching import MATCHING_SCALE, dequantize
from .source_views import SourceView

MIN_SOURCE_Z = 1e-6  # a projected hypothesis must lie in front of the source camera


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



def _sweep_mask_or_all(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, np.bool_)
    if not isinstance(mask, np.ndarray) or mask.shape != shape:
        raise ValueError(f"mask: expected a bool array of shape {list(shape)} (the sweep resolution), got "
                         f"{list(getattr(mask, 'shape', []))}")
    return np.ascontiguousarray(mask, dtype=np.bool_)

