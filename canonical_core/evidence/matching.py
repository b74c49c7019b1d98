"""Training-free matching features for the plane sweep (multi-view depth), distinct from F_view.

The fused descriptor F_view (`features.py`, 16 channels, unit norm) is built to say whether two
observations of one voxel agree; it is too smooth to *find* the correspondence, and its unit norm
bounds the paper's score <F_i, F_j> / sqrt(L) to [-1/4, 1/4], so the softmax over hypotheses is
nearly uniform (U_pos ~ the whole depth range), and its arg-max finds the sensor's depth less
often than these features do (tests/evidence/test_mvs_shelf.py holds that). The sweep therefore
uses its own features (the "L used by the sweep can differ from the L that is fused"):

**Band-limited normalised patches on a luminance pyramid.** For each level with spacing f in
``MATCHING_LEVELS`` the luminance (at sweep resolution) is box-blurred over f pixels and sampled on
a 7 x 7 grid of spacing f around the pixel (support 7 f pixels); the grid is projected onto the 2D
DCT basis functions of order 1 <= i + j <= ``DCT_CUTOFF`` (20 functions: the mean is dropped, the
highest frequencies, mostly noise, too), and the coefficients are divided by
sqrt(band energy / 49 + ``CONTRAST_FLOOR``^2). So <f_l(a), f_l(b)> / 49 is a low-pass normalised
cross-correlation NCC_l in [-1, 1], and a flat (textureless, under-exposed) patch has a small vector
that scores ~0 against everything: its hypotheses stay near-uniform and its U_pos high, which is
the honest answer. Fine levels localise, coarse levels (35-56 px support) disambiguate weak and
repetitive texture. Coarse levels (spacing >= ``EDGE_AWARE_FROM``) are edge-aware: each sample is
weighted by ~exp(-(its luminance - the centre's)^2 / (2 ``EDGE_SIGMA``^2)) before the weighted mean
is removed, so a coarse patch describes mostly the centre's own surface and depth edges fatten less.

The grid size, the levels and the edge-aware coarse levels were chosen by the sweep's median
AbsRel against sensor depth (the variants tried and their figures: docs/experiments.md, "Matching
features").

**Temperature.** The features are scaled so that the paper's score is

    <F_i, F_j> / sqrt(L) = MATCH_SHARPNESS * sum_l NCC_l        (L = 5 levels x 20 = 100)

i.e. ``MATCH_SHARPNESS`` logits per unit of correlation and level. With unit-norm features the
softmax is flat (U_pos spans the depth range); a higher sharpness snaps D to the arg-max (slightly
lower median error) but makes wrong peaks confident (higher AUSE); 28 is the balance that
bench/depth.py's table "Sharpness" shows.

**Storage.** Features are quantised to int8 (``MATCHING_QUANT`` per step; entries are bounded by
7 in magnitude, so the step is ~1/20 of a typical entry) so a window of source views costs
h * w * 100 bytes per view (7.7 MB for a 640x480 frame swept at half resolution); F = MATCHING_SCALE
* q exactly, so snapshots are bit-exact and the fast and reference sweeps see the same numbers.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

PATCH_RADIUS = 3  # 7 x 7 sample grid per level
MATCHING_LEVELS = (1, 2, 3, 5, 8)  # blur / sample spacing per level, in sweep-resolution pixels
DCT_CUTOFF = 5  # keep DCT functions of order 1 <= i + j <= 5 (20 per level)
CONTRAST_FLOOR = 0.005  # luminance contrast below which a patch counts as flat
EDGE_AWARE_FROM = 4  # levels with spacing >= this weight their samples by similarity to the centre
EDGE_SIGMA = 0.15  # luminance difference (of the blurred image) at which a sample's weight is exp(-1/2)
MATCH_SHARPNESS = 28.0  # logits per unit of NCC per level
MATCHING_QUANT = 8.0 / 127.0  # int8 step of the normalised coefficients (range +-8 > max 7)
_LUMA = (0.299, 0.587, 0.114)


def _dct_vectors(n: int) -> np.ndarray:  # [n, n] float64: row k = orthonormal 1D DCT-II vector of order k
    x = np.arange(n)
    c = np.stack([np.cos(np.pi * (x + 0.5) * k / n) for k in range(n)])
    return c / np.linalg.norm(c, axis=1, keepdims=True)


_N = 2 * PATCH_RADIUS + 1
# 2D basis function (i, j) = outer(c_i over rows, c_j over columns), for 1 <= i + j <= DCT_CUTOFF
_ORDERS = [(i, s - i) for s in range(1, DCT_CUTOFF + 1) for i in range(s + 1) if i < _N and s - i < _N]
_C = torch.from_numpy(_dct_vectors(_N).astype(np.float32))
_NUM_H = max(j for _, j in _ORDERS) + 1
_H_KERNELS = _C[:_NUM_H].view(_NUM_H, 1, 1, _N)  # horizontal pass, one per column order j
_V_KERNELS = torch.stack([_C[i] for i, _ in _ORDERS]).view(len(_ORDERS), 1, _N, 1)  # vertical pass per (i, j)
_V_INPUT = torch.tensor([j for _, j in _ORDERS])
MATCHING_FEATURE_DIM = len(_ORDERS) * len(MATCHING_LEVELS)
# F = MATCHING_SCALE * q with <F_i, F_j> / sqrt(L) = MATCH_SHARPNESS * sum_l <f_l, f_l'> / n^2
MATCHING_SCALE = MATCHING_QUANT * math.sqrt(MATCH_SHARPNESS * math.sqrt(MATCHING_FEATURE_DIM) / _N**2)


def dct_basis() -> np.ndarray:  # [M, n, n] float64
    """The 2D basis functions the coefficients of one level are taken on (for tests and docs)."""
    c = _dct_vectors(_N)
    return np.stack([np.outer(c[i], c[j]) for i, j in _ORDERS])


_BASIS_FLAT = torch.from_numpy(dct_basis().reshape(len(_ORDERS), -1).astype(np.float32))  # [M, n*n]


def _rgb_tensor(rgb: Tensor | np.ndarray) -> Tensor:  # [H, W, 3] uint8, checked
    t = torch.as_tensor(np.asarray(rgb) if not isinstance(rgb, Tensor) else rgb)
    if t.ndim != 3 or t.shape[-1] != 3 or t.dtype != torch.uint8:
        raise ValueError(f"rgb: expected uint8 [H, W, 3], got {t.dtype} {list(t.shape)}")
    return t


def resize_image(
    rgb: Tensor | np.ndarray,  # [H, W, 3] uint8
    size: tuple[int, int],  # (h, w)
) -> Tensor:  # [h, w, 3] float32 in [0, 1]
    """Anti-aliased bilinear resize (pixel-centre convention, as `Camera.scaled`)."""
    t = _rgb_tensor(rgb)
    img = t.permute(2, 0, 1)[None].float() / 255.0
    if tuple(img.shape[-2:]) != tuple(size):
        img = F.interpolate(img, size=tuple(size), mode="bilinear", antialias=True, align_corners=False)
    return img[0].permute(1, 2, 0).contiguous()


def _edge_weight(d: Tensor) -> Tensor:
    """Weight of a sample whose (blurred) luminance differs by d from the centre's: (1 + t/4)^-4
    with t = d^2 / (2 EDGE_SIGMA^2), a rational stand-in for exp(-t) (same value and slope at 0,
    no transcendental function in the per-sample loop of the fast path)."""
    q = (1.0 + d.square() * (0.25 / (2 * EDGE_SIGMA**2))).square()
    return 1.0 / q.square()


def _luminance(image) -> Tensor:  # [h, w] float32 from [h, w] luminance or [h, w, 3] RGB (float in [0, 1] or uint8)
    t = torch.from_numpy(np.ascontiguousarray(image)) if isinstance(image, np.ndarray) else torch.as_tensor(image)
    if t.dtype == torch.uint8:
        t = t.float() / 255.0
    if t.ndim == 3 and t.shape[-1] == 3:
        t = t.float() @ torch.tensor(_LUMA)
    if t.ndim != 2:
        raise ValueError(f"image: expected a luminance [h, w] or an RGB image [h, w, 3], got {list(t.shape)}")
    return t.float().contiguous()


@numba.njit(parallel=True, cache=True)
def _luma_half_kernel(rgb, out):
    # out[v, u] = luminance averaged over the 2 x 2 block (2v.., 2u..) of the uint8 image, in [0, 1]
    h, w = out.shape
    for v in numba.prange(h):
        for u in range(w):
            acc = np.float32(0.0)
            for dy in range(2):
                for dx in range(2):
                    p = rgb[2 * v + dy, 2 * u + dx]
                    acc += (np.float32(0.299) * np.float32(p[0]) + np.float32(0.587) * np.float32(p[1])
                            + np.float32(0.114) * np.float32(p[2]))
            out[v, u] = acc * np.float32(1.0 / (4.0 * 255.0))


def sweep_luminance(
    rgb: Tensor | np.ndarray,  # [H, W, 3] uint8
    size: tuple[int, int],  # (h, w) of the sweep camera
) -> np.ndarray:  # [h, w] float32 luminance in [0, 1]
    """The luminance the matching features are computed from, at sweep resolution.

    Half resolution (the default scale) is a 2 x 2 block average (numba); other sizes use the
    anti-aliased bilinear resize of `resize_image` on the luminance. Both keep pixel centres where
    `Camera.scaled` puts them.
    """
    t = _rgb_tensor(rgb)
    H, W = int(t.shape[0]), int(t.shape[1])
    h, w = int(size[0]), int(size[1])
    if 0 <= H - 2 * h <= 1 and 0 <= W - 2 * w <= 1 and h > 0 and w > 0:
        out = np.empty((h, w), np.float32)
        _luma_half_kernel(t.numpy(), out)
        return out
    luma = _luminance(t)[None, None]
    if (H, W) != (h, w):
        luma = F.interpolate(luma, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
    return np.ascontiguousarray(luma[0, 0].numpy(), dtype=np.float32)


def _box_blur(y: Tensor, f: int) -> Tensor:  # [1, 1, h, w] -> same; symmetric box of width f (replicate borders)
    if f == 1:
        return y
    k = torch.from_numpy(_blur_taps(f))
    r = (k.numel() - 1) // 2
    y = F.conv2d(F.pad(y, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))


def matching_coefficients(
    image: Tensor | np.ndarray,  # [h, w] luminance or [h, w, 3] RGB in [0, 1] (or uint8), at sweep resolution
) -> Tensor:  # [h, w, L] float32, the normalised band-limited patches (before scaling)
    """Per-level normalised DCT coefficients f_l (entries within +-7); see the module docstring.
    Pure PyTorch: the definition `matching_features` is held to."""
    luma = _luminance(image)[None, None]  # [1, 1, h, w]
    h, w = luma.shape[-2:]
    out = []
    for f in MATCHING_LEVELS:
        pad = PATCH_RADIUS * f
        x = _box_blur(luma, f)
        y = F.pad(x, (pad, pad, pad, pad), mode="replicate")
        if f >= EDGE_AWARE_FROM:
            # edge-aware: samples unlike the centre (another surface) are down-weighted before the
            # (weighted) mean is removed, so a coarse patch describes mostly the centre's surface
            samples = F.unfold(y, _N, dilation=f)[0]  # [n*n, h*w], row-major over the 7 x 7 grid
            wgt = _edge_weight(samples - x.reshape(1, -1))
            mean = (wgt * samples).sum(0, keepdim=True) / wgt.sum(0, keepdim=True)
            c = (_BASIS_FLAT @ ((samples - mean) * wgt)).reshape(-1, h, w)  # [M, h, w]
        else:
            # separable: the 2D DCT functions are outer products of 1D ones
            hx = F.conv2d(y, _H_KERNELS, dilation=(1, f))  # [1, J, h + 2 pad, w]
            c = F.conv2d(hx[:, _V_INPUT], _V_KERNELS, dilation=(f, 1), groups=len(_ORDERS))[0]  # [M, h, w]
        energy = c.square().sum(0, keepdim=True) / _N**2
        out.append(c / (energy + CONTRAST_FLOOR**2).sqrt())
    return torch.cat(out).permute(1, 2, 0).contiguous()


def _blur_taps(f: int) -> np.ndarray:  # [T] float32, the 1D box of `_box_blur`
    if f == 1:
        return np.ones(1, np.float32)
    if f % 2:
        return np.full(f, 1.0 / f, np.float32)
    # even width: f + 1 taps with half weights at the ends, so the blur stays centred
    k = np.ones(f + 1, np.float32)
    k[0] = k[-1] = 0.5
    return k / f


@numba.njit(parallel=True, cache=True)
def _blur_kernel(luma, taps, num_taps, out):
    # out[l] = separable box blur of luma with taps[l, :num_taps[l]] (replicate borders), all levels at once
    h, w = luma.shape
    for v in numba.prange(h):
        for l in range(taps.shape[0]):
            n = num_taps[l]
            r = (n - 1) // 2
            for u in range(w):
                acc = np.float32(0.0)
                for a in range(n):
                    vv = min(max(v + a - r, 0), h - 1)
                    row = np.float32(0.0)
                    for b in range(n):
                        row += taps[l, b] * luma[vv, min(max(u + b - r, 0), w - 1)]
                    acc += taps[l, a] * row
                out[l, v, u] = acc


@numba.njit(parallel=True, cache=True)
def _horizontal_kernel(blurred, levels, C, radius, hx):
    # hx[l, j, v, u] = sum_b C[j, b] * blurred[l, v, clamp(u + (b - radius) * level_l)]
    nl, h, w = blurred.shape
    n = 2 * radius + 1
    J = hx.shape[1]
    for v in numba.prange(h):
        for l in range(nl):
            f = levels[l]
            for u in range(w):
                for j in range(J):
                    hx[l, j, v, u] = np.float32(0.0)
                for b in range(n):
                    x = blurred[l, v, min(max(u + (b - radius) * f, 0), w - 1)]
                    for j in range(J):
                        hx[l, j, v, u] += C[j, b] * x


@numba.njit(parallel=True, cache=True)
def _vertical_kernel(hx, levels, slots, C, orders_i, orders_j, radius, floor2, quant, out):
    # coefficient (i, j) of level l = sum_a C[i, a] * hx[l, j, clamp(v + (a - radius) * level_l), u];
    # normalised by sqrt(energy / n^2 + floor^2), quantised to int8 into out[v, u, slots[l] * M + m]
    nl, h, w = hx.shape[0], hx.shape[2], hx.shape[3]
    n = 2 * radius + 1
    M = orders_i.shape[0]
    inv_nn = np.float32(1.0 / (n * n))
    for v in numba.prange(h):
        coef = np.empty((M, w), np.float32)
        inv = np.empty(w, np.float32)
        rows = np.empty(n, np.int64)
        for l in range(nl):
            for a in range(n):
                rows[a] = min(max(v + (a - radius) * levels[l], 0), h - 1)
            coef[:] = 0.0
            for m in range(M):  # loops ordered so that the inner one runs along u (vectorises)
                i, j = orders_i[m], orders_j[m]
                for a in range(n):
                    c = C[i, a]
                    src = hx[l, j, rows[a]]
                    for u in range(w):
                        coef[m, u] += c * src[u]
            for u in range(w):
                energy = np.float32(0.0)
                for m in range(M):
                    energy += coef[m, u] * coef[m, u]
                inv[u] = np.float32(1.0) / (np.sqrt(energy * inv_nn + floor2) * quant)
            for u in range(w):
                for m in range(M):
                    q = np.float32(np.round(coef[m, u] * inv[u]))
                    out[v, u, slots[l] * M + m] = np.int8(min(max(q, np.float32(-127.0)), np.float32(127.0)))


@numba.njit(parallel=True, cache=True)
def _edge_aware_kernel(blurred, level, C, num_h, orders_i, orders_j, radius, inv_2s2, floor2, quant, out, slot):
    # one edge-aware level: weighted 7 x 7 samples, weighted mean removed, separable DCT, normalise,
    # quantise; per row, every step runs along u in the innermost loop (vectorises)
    h, w = blurred.shape
    n = 2 * radius + 1
    M = orders_i.shape[0]
    inv_nn = np.float32(1.0 / (n * n))
    cols = np.empty((n, w), np.int64)
    for b in range(n):
        for u in range(w):
            cols[b, u] = min(max(u + (b - radius) * level, 0), w - 1)
    for v in numba.prange(h):
        samples = np.empty((n, n, w), np.float32)
        weights = np.empty((n, n, w), np.float32)
        hx = np.zeros((n, num_h, w), np.float32)
        coef = np.zeros((M, w), np.float32)
        sw = np.zeros(w, np.float32)
        sws = np.zeros(w, np.float32)
        for a in range(n):
            row = blurred[min(max(v + (a - radius) * level, 0), h - 1)]
            for b in range(n):
                for u in range(w):
                    x = row[cols[b, u]]
                    q = np.float32(1.0) + (x - blurred[v, u]) * (x - blurred[v, u]) * inv_2s2 * np.float32(0.25)
                    q = q * q
                    wt = np.float32(1.0) / (q * q)  # (1 + t / 4)^-4, t = d^2 / (2 sigma^2): see _edge_weight
                    samples[a, b, u] = x
                    weights[a, b, u] = wt
                    sw[u] += wt
                    sws[u] += wt * x
        for u in range(w):
            sws[u] = sws[u] / sw[u]  # the weighted mean
        for a in range(n):
            for b in range(n):
                for u in range(w):
                    samples[a, b, u] = (samples[a, b, u] - sws[u]) * weights[a, b, u]
            for j in range(num_h):
                for b in range(n):
                    c = C[j, b]
                    for u in range(w):
                        hx[a, j, u] += c * samples[a, b, u]
        for m in range(M):
            i, j = orders_i[m], orders_j[m]
            for a in range(n):
                c = C[i, a]
                for u in range(w):
                    coef[m, u] += c * hx[a, j, u]
        for u in range(w):
            energy = np.float32(0.0)
            for m in range(M):
                energy += coef[m, u] * coef[m, u]
            inv = np.float32(1.0) / (np.sqrt(energy * inv_nn + floor2) * quant)
            for m in range(M):
                q = np.float32(np.round(coef[m, u] * inv))
                out[v, u, slot * M + m] = np.int8(min(max(q, np.float32(-127.0)), np.float32(127.0)))


_C_NP = _dct_vectors(_N).astype(np.float32)
_ORDERS_I = np.array([i for i, _ in _ORDERS], np.int64)
_ORDERS_J = np.array([j for _, j in _ORDERS], np.int64)
_LEVELS_NP = np.array(MATCHING_LEVELS, np.int64)
_TAPS = np.zeros((len(MATCHING_LEVELS), max(len(_blur_taps(f)) for f in MATCHING_LEVELS)), np.float32)
for _l, _f in enumerate(MATCHING_LEVELS):
    _TAPS[_l, : len(_blur_taps(_f))] = _blur_taps(_f)
_NUM_TAPS = np.array([len(_blur_taps(f)) for f in MATCHING_LEVELS], np.int64)
_PLAIN_SLOTS = np.array([i for i, f in enumerate(MATCHING_LEVELS) if f < EDGE_AWARE_FROM], np.int64)
_EDGE_SLOTS = np.array([i for i, f in enumerate(MATCHING_LEVELS) if f >= EDGE_AWARE_FROM], np.int64)


def matching_features(
    image: Tensor | np.ndarray,  # [h, w] luminance or [h, w, 3] RGB in [0, 1] (or uint8), at sweep resolution
) -> np.ndarray:  # [h, w, L] int8; the feature is F = MATCHING_SCALE * q
    """Quantised matching features of an image already at sweep resolution (numba fast path of
    round(`matching_coefficients` / MATCHING_QUANT), clamped to +-127; deterministic)."""
    luma = np.ascontiguousarray(_luminance(image).numpy(), dtype=np.float32)
    h, w = luma.shape
    nl = len(MATCHING_LEVELS)
    blurred = np.empty((nl, h, w), np.float32)
    out = np.empty((h, w, MATCHING_FEATURE_DIM), np.int8)
    _blur_kernel(luma, _TAPS, _NUM_TAPS, blurred)
    floor2, quant = np.float32(CONTRAST_FLOOR**2), np.float32(MATCHING_QUANT)
    plain = _PLAIN_SLOTS
    if plain.size:
        hx = np.empty((plain.size, _NUM_H, h, w), np.float32)
        sub = np.ascontiguousarray(blurred[plain])
        _horizontal_kernel(sub, _LEVELS_NP[plain], _C_NP, PATCH_RADIUS, hx)
        _vertical_kernel(hx, _LEVELS_NP[plain], plain, _C_NP, _ORDERS_I, _ORDERS_J, PATCH_RADIUS, floor2, quant, out)
    for slot in _EDGE_SLOTS:
        _edge_aware_kernel(blurred[slot], int(_LEVELS_NP[slot]), _C_NP, _NUM_H, _ORDERS_I, _ORDERS_J, PATCH_RADIUS,
                           np.float32(1.0 / (2 * EDGE_SIGMA**2)), floor2, quant, out, int(slot))
    return out


def matching_features_reference(
    image: Tensor | np.ndarray,  # [h, w] luminance or [h, w, 3] RGB, at sweep resolution
) -> np.ndarray:  # [h, w, L] int8
    """Pure-PyTorch definition of `matching_features`."""
    q = torch.round(matching_coefficients(image) / MATCHING_QUANT).clamp_(-127, 127)
    return q.to(torch.int8).numpy()


def dequantize(q: np.ndarray | Tensor) -> Tensor:  # [..., L] int8 -> float32 F
    """The float features F = MATCHING_SCALE * q that the paper's score uses."""
    return torch.as_tensor(q).float() * MATCHING_SCALE


__all__ = ["MATCHING_FEATURE_DIM", "MATCHING_LEVELS", "MATCH_SHARPNESS", "MATCHING_SCALE", "matching_features",
           "matching_features_reference", "matching_coefficients", "resize_image", "sweep_luminance", "dequantize"]
