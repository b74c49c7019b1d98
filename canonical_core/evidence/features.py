"""Training-free per-pixel descriptors (the default F_view backend) and client-feature sampling.

The default descriptor is 16 channels built from 13 raw pixels around each pixel: a centre cross
(the pixel and its 4 neighbours) and a ring of 8 samples at radius ``RING_RADIUS``:

    [0:3]   opponent colour of the centre cross   (Y - 0.5, R - G, B - (R + G) / 2)
    [3:6]   opponent colour of the ring mean        (context)
    [6:14]  ring luminance minus centre luminance, divided by (ring contrast + 0.05)
            (the local texture pattern, invariant to exposure changes)
    [14]    ring contrast (root mean square of the ring's luminance differences)
    [15]    centre-surround luminance difference

scaled per block and L2-normalised, so cos(F_a, F_b) is a dot product. Observations of one surface
point from two nearby views get similar descriptors; a mixed pixel on a depth edge or a
mis-registered observation does not. ``default_features_reference`` is the whole-image PyTorch
definition; ``default_features_at`` is the numba fast path evaluated only at the pixels a fold uses,
held to the reference by the tests.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..frame import Frame

DEFAULT_FEATURE_DIM = 16
RING_RADIUS = 3
# (dv, du) offsets: the 8-ring at RING_RADIUS, in a fixed order.
RING_OFFSETS = np.array(
    [(-RING_RADIUS, -RING_RADIUS), (-RING_RADIUS, 0), (-RING_RADIUS, RING_RADIUS), (0, RING_RADIUS),
     (RING_RADIUS, RING_RADIUS), (RING_RADIUS, 0), (RING_RADIUS, -RING_RADIUS), (0, -RING_RADIUS)],
    dtype=np.int64,
)
CROSS_OFFSETS = np.array([(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)], dtype=np.int64)
# block weights: colour dominates, texture and context refine (chosen so that colour alone
# decides between clearly different surfaces and texture breaks ties on similar colours).
W_COLOUR, W_CONTEXT, W_PATTERN, W_ENERGY, W_SURROUND = 1.0, 0.5, 0.35, 1.0, 1.0
CONTRAST_FLOOR = 0.05


def _opponent(rgb: Tensor) -> Tensor:  # [..., 3] in [0, 1] -> [..., 3]
    r, g, b = rgb.unbind(-1)
    y = 0.299 * r + 0.587 * g + 0.114 * b
    return torch.stack([y - 0.5, r - g, b - 0.5 * (r + g)], -1)


def default_features_reference(
    rgb: Tensor,  # [H, W, 3] uint8
) -> Tensor:  # [H, W, 16] float32, unit norm
    """The default descriptor at every pixel (pure PyTorch; borders replicate-padded).

    Example:
        >>> f = default_features_reference(torch.zeros(8, 8, 3, dtype=torch.uint8))
        >>> f.shape, bool(torch.allclose(f.norm(dim=-1), torch.ones(8, 8)))
        (torch.Size([8, 8, 16]), True)
    """
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.dtype != torch.uint8:
        raise ValueError(f"rgb: expected uint8 [H, W, 3], got {rgb.dtype} {list(rgb.shape)}")
    H, W = rgb.shape[:2]
    img = rgb.float() / 255.0
    pad = RING_RADIUS
    padded = F.pad(img.permute(2, 0, 1)[None], (pad, pad, pad, pad), mode="replicate")[0].permute(1, 2, 0)

    def shifted(dv: int, du: int) -> Tensor:  # [H, W, 3]: img[v + dv, u + du], clamped
        return padded[pad + dv: pad + dv + H, pad + du: pad + du + W]

    centre = torch.stack([shifted(int(dv), int(du)) for dv, du in CROSS_OFFSETS]).mean(0)
    ring = torch.stack([shifted(int(dv), int(du)) for dv, du in RING_OFFSETS])  # [8, H, W, 3]
    luma = torch.tensor([0.299, 0.587, 0.114])
    yc = centre @ luma
    yr = ring @ luma  # [8, H, W]
    diff = yr - yc
    energy = diff.square().mean(0).sqrt()
    pattern = (diff / (energy + CONTRAST_FLOOR)).permute(1, 2, 0)
    context = ring.mean(0)
    surround = context @ luma - yc
    feat = torch.cat(
        [
            W_COLOUR * _opponent(centre),
            W_CONTEXT * _opponent(context),
            W_PATTERN * pattern,
            W_ENERGY * energy[..., None],
            W_SURROUND * surround[..., None],
        ],
        -1,
    )
    return feat / feat.norm(dim=-1, keepdim=True).clamp_min(1e-12)


_RING_DV = tuple(int(x) for x in RING_OFFSETS[:, 0])
_RING_DU = tuple(int(x) for x in RING_OFFSETS[:, 1])


_BLOCK = 64  # pixels per block of the fast path


@numba.njit(parallel=True, cache=True)
def _default_features_kernel(rgb, rows, cols, out):
    # Blocks of pixels in two stages: gather the 13 raw samples' integer sums and ring luminances
    # into a [rows, block] scratch (a scalar loop), then do the arithmetic over the block in
    # straight loops the compiler vectorises. Same values as the reference up to float rounding.
    H, W = rgb.shape[0], rgb.shape[1]
    flat = rgb.reshape(-1)
    n = rows.shape[0]
    inv255 = np.float32(1.0 / 255.0)
    for blk in numba.prange((n + _BLOCK - 1) // _BLOCK):
        i0 = blk * _BLOCK
        m = min(_BLOCK, n - i0)
        # rows of s: 0-2 centre-cross colour, 3-5 ring colour (sums, then means), 6-13 ring luminance
        # minus centre luminance, 14 ring energy^2, 15 centre luminance, 16-21 opponent colours
        s = np.zeros((22, _BLOCK), np.float32)
        for j in range(m):
            v, u = rows[i0 + j], cols[i0 + j]
            v0, v1 = max(v - 1, 0), min(v + 1, H - 1)
            u0, u1 = max(u - 1, 0), min(u + 1, W - 1)
            p0, p1, p2 = (v * W + u) * 3, (v0 * W + u) * 3, (v1 * W + u) * 3
            p3, p4 = (v * W + u0) * 3, (v * W + u1) * 3
            for c in range(3):
                s[c, j] = np.float32(np.int32(flat[p0 + c]) + np.int32(flat[p1 + c]) + np.int32(flat[p2 + c])
                                     + np.int32(flat[p3 + c]) + np.int32(flat[p4 + c]))
            sr, sg, sb = np.int32(0), np.int32(0), np.int32(0)
            for k in range(8):
                p = (min(max(v + _RING_DV[k], 0), H - 1) * W + min(max(u + _RING_DU[k], 0), W - 1)) * 3
                r, g, b = np.int32(flat[p]), np.int32(flat[p + 1]), np.int32(flat[p + 2])
                sr, sg, sb = sr + r, sg + g, sb + b
                s[6 + k, j] = np.float32(0.299) * np.float32(r) + np.float32(0.587) * np.float32(g) + np.float32(0.114) * np.float32(b)
            s[3, j], s[4, j], s[5, j] = np.float32(sr), np.float32(sg), np.float32(sb)
        for c in range(3):
            for j in range(_BLOCK):
                s[c, j] *= inv255 / np.float32(5.0)
                s[3 + c, j] *= inv255 / np.float32(8.0)
        for j in range(_BLOCK):
            s[15, j] = np.float32(0.299) * s[0, j] + np.float32(0.587) * s[1, j] + np.float32(0.114) * s[2, j]
        for k in range(6, 14):
            for j in range(_BLOCK):
                s[k, j] = s[k, j] * inv255 - s[15, j]
                s[14, j] += s[k, j] * s[k, j]
        for j in range(_BLOCK):
            cr, cg, cb, mr, mg, mb, yc = s[0, j], s[1, j], s[2, j], s[3, j], s[4, j], s[5, j], s[15, j]
            yr = np.float32(0.299) * mr + np.float32(0.587) * mg + np.float32(0.114) * mb
            energy = np.sqrt(s[14, j] / np.float32(8.0))
            s[16, j] = np.float32(W_COLOUR) * (yc - np.float32(0.5))
            s[17, j] = np.float32(W_COLOUR) * (cr - cg)
            s[18, j] = np.float32(W_COLOUR) * (cb - np.float32(0.5) * (cr + cg))
            s[19, j] = np.float32(W_CONTEXT) * (yr - np.float32(0.5))
            s[20, j] = np.float32(W_CONTEXT) * (mr - mg)
            s[21, j] = np.float32(W_CONTEXT) * (mb - np.float32(0.5) * (mr + mg))
            scale = np.float32(W_PATTERN) / (energy + np.float32(CONTRAST_FLOOR))
            f14 = np.float32(W_ENERGY) * energy
            f15 = np.float32(W_SURROUND) * (yr - yc)
            n2 = f14 * f14 + f15 * f15 + scale * scale * s[14, j]
            for c in range(16, 22):
                n2 += s[c, j] * s[c, j]
            inv = np.float32(1.0) / max(np.sqrt(n2), np.float32(1e-12))
            # reuse rows 0-3: the last two channels, the pattern scale and the normaliser
            s[0, j], s[1, j], s[2, j], s[3, j] = f14 * inv, f15 * inv, scale * inv, inv
        for j in range(m):
            o = out[i0 + j]
            for c in range(6):
                o[c] = s[16 + c, j] * s[3, j]
            for k in range(8):
                o[6 + k] = s[6 + k, j] * s[2, j]
            o[14], o[15] = s[0, j], s[1, j]


def default_features_at(
    rgb: np.ndarray,  # [H, W, 3] uint8
    rows: np.ndarray,  # [M] int pixel rows (v)
    cols: np.ndarray,  # [M] int pixel columns (u)
) -> np.ndarray:  # [M, 16] float32
    """The default descriptor at selected pixels (numba fast path of `default_features_reference`)."""
    out = np.empty((rows.shape[0], DEFAULT_FEATURE_DIM), np.float32)
    _default_features_kernel(np.ascontiguousarray(rgb), rows.astype(np.int64, copy=False), cols.astype(np.int64, copy=False), out)
    return out


def projection_matrix(in_dim: int, out_dim: int) -> np.ndarray:  # [in_dim, out_dim] float32
    """A fixed orthonormal-column projection (seeded by the sizes) that maps descriptors to L channels.

    Rows are orthonormal when ``in_dim <= out_dim`` (so cosines are preserved exactly); otherwise
    columns are orthonormal (a random subspace, cosines preserved on average).
    """
    rng = np.random.default_rng(1_000_003 * in_dim + out_dim)
    a = rng.standard_normal((max(in_dim, out_dim), min(in_dim, out_dim)))
    q, _ = np.linalg.qr(a)
    return (q if in_dim >= out_dim else q.T).astype(np.float32)


def sample_client_features(
    features: np.ndarray,  # [H', W', C] float32
    rows: np.ndarray,  # [M] pixel rows of the full-size image
    cols: np.ndarray,  # [M] pixel columns
    image_size: tuple[int, int],  # (H, W) of the frame's image
) -> np.ndarray:  # [M, C]
    """Nearest-neighbour lookup of a client feature map of any resolution at full-image pixels."""
    H, W = image_size
    h, w = features.shape[:2]
    # pixel-centre convention: full-image pixel u covers [u - 0.5, u + 0.5] -> map centres.
    fr = np.clip(np.floor((rows + 0.5) * (h / H)).astype(np.int64), 0, h - 1)
    fc = np.clip(np.floor((cols + 0.5) * (w / W)).astype(np.int64), 0, w - 1)
    return features[fr, fc]


def sample_client_labels(
    frame: Frame,
    rows: np.ndarray,  # [M] pixel rows of the full-size image
    cols: np.ndarray,  # [M] pixel columns
) -> np.ndarray | None:  # [M, S] float32
    """A frame's label scores at full-image pixels, looked up nearest as client features are; a class
    map's as one-hot rows over its ``num_classes`` (all 0 where it has no class). None without labels."""
    if frame.labels is None:
        return None
    size = (frame.height, frame.width)
    if frame.labels.ndim == 3:
        return np.ascontiguousarray(sample_client_features(frame.labels.numpy(), rows, cols, size))
    ids = sample_client_features(frame.labels.numpy()[..., None], rows, cols, size)  # [M, 1]
    return (ids == np.arange(frame.num_classes, dtype=ids.dtype)).astype(np.float32)
