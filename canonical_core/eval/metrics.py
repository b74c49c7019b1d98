"""Image metrics of the evaluation: PSNR (all pixels or a mask), SSIM, coverage and the all-pixel
PSNR it allows, depth agreement, the depth-edge mask that splits PSNR into edge and flat pixels,
feature cosine.

Images are float tensors [H, W, C] with values in [0, 1] (peak signal 1). A pixel is *covered*
when the method drew something there: accumulated opacity >= ``COVERAGE_THRESHOLD``.

Example:
    >>> import torch
    >>> a = torch.full((16, 16, 3), 0.5)
    >>> psnr(a, a), round(psnr(a, a + 0.1), 2), round(ssim(a, a), 6)
    (inf, 20.0, 1.0)
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import Tensor

from ..decode.colour_solve import COVERED_ALPHA as COVERAGE_THRESHOLD  # the colour solve's covered pixels

DEPTH_TOLERANCE_VOXELS = 2.0  # rendered depth "agrees" with the held-out sensor depth within 2 voxels
EDGE_JUMP = 0.05  # a depth edge: a jump to a neighbour over 5 % of the nearer depth
EDGE_RADIUS = 3  # pixels: "edge" pixels lie within this (square) distance of a depth edge or a hole

# SSIM as defined by Wang, Bovik, Sheikh and Simoncelli (2004): an 11x11 Gaussian window with
# sigma 1.5, C1 = (K1 L)^2, C2 = (K2 L)^2 with K1 = 0.01, K2 = 0.03 and dynamic range L = 1,
# statistics over "valid" windows (no padding), the SSIM map averaged over windows and channels.
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def _check_pair(pred: Tensor, target: Tensor) -> None:
    for name, t in (("pred", pred), ("target", target)):
        if not isinstance(t, Tensor) or t.ndim != 3:
            got = list(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name}: expected an image tensor [H, W, C], got {got}")
    if pred.shape != target.shape:
        raise ValueError(f"pred: shape {list(pred.shape)} differs from target {list(target.shape)}")


def psnr(
    pred: Tensor,  # [H, W, C] in [0, 1]
    target: Tensor,  # [H, W, C] in [0, 1]
    mask: Tensor | None = None,  # [H, W] bool: only these pixels count
) -> float:
    """Peak signal-to-noise ratio in dB, -10 log10(MSE), over all pixels or the ``mask``ed ones.

    Returns ``inf`` for identical images and ``nan`` for an empty mask (no pixel to compare).
    """
    _check_pair(pred, target)
    err = (pred.double() - target.double()) ** 2  # [H, W, C]
    if mask is not None:
        if mask.shape != pred.shape[:2] or mask.dtype != torch.bool:
            raise ValueError(f"mask: expected a bool tensor of shape {list(pred.shape[:2])}, got {mask.dtype} {list(mask.shape)}")
        if not bool(mask.any()):
            return math.nan
        err = err[mask]
    mse = float(err.mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def _gaussian_window(size: int, sigma: float) -> Tensor:  # [size] float64, sums to 1
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    w = torch.exp(-(x**2) / (2 * sigma**2))
    return w / w.sum()


@numba.njit(parallel=True, cache=True)
def _blur_valid_kernel(img, g, out):  # [C, H, W] float64, [k] -> [C, H - k + 1, W - k + 1], no padding
    # separable, in float64 (torch's grouped float64 convolution takes seconds per image on a CPU)
    C, H, W = img.shape
    k = g.shape[0]
    wo = W - k + 1
    rows = np.empty((C, H, wo))
    for n in numba.prange(C * H):
        ch, v = n // H, n % H
        for u in range(wo):
            acc = 0.0
            for j in range(k):
                acc += g[j] * img[ch, v, u + j]
            rows[ch, v, u] = acc
    for n in numba.prange(C * out.shape[1]):
        ch, v = n // out.shape[1], n % out.shape[1]
        for u in range(wo):
            acc = 0.0
            for j in range(k):
                acc += g[j] * rows[ch, v + j, u]
            out[ch, v, u] = acc


def ssim(
    pred: Tensor,  # [H, W, C] in [0, 1]
    target: Tensor,  # [H, W, C] in [0, 1]
) -> float:
    """Mean structural similarity (Wang et al. 2004; constants above), 1.0 for identical images."""
    _check_pair(pred, target)
    h, w, c = pred.shape
    if min(h, w) < SSIM_WINDOW:
        raise ValueError(f"pred: SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {w}x{h}")
    g = _gaussian_window(SSIM_WINDOW, SSIM_SIGMA).numpy()

    def blur(t: Tensor) -> Tensor:  # [1, C, H, W] -> [1, C, H - 10, W - 10]
        out = np.empty((c, h - SSIM_WINDOW + 1, w - SSIM_WINDOW + 1))
        _blur_valid_kernel(np.ascontiguousarray(t[0].numpy()), g, out)
        return torch.from_numpy(out)[None]

    return float(mean_ssim(pred.double().permute(2, 0, 1)[None], target.double().permute(2, 0, 1)[None], blur))


def mean_ssim(
    x: Tensor,  # [1, C, H, W]
    y: Tensor,  # [1, C, H, W]
    blur,  # [1, C, H, W] -> [1, C, H', W']: the SSIM window's Gaussian average at every valid position
) -> Tensor:  # [] the mean of the SSIM map
    """SSIM's formula over the local means, variances and covariance that ``blur`` gives (the metric's
    blur is a float64 numba kernel; the training loss's a differentiable convolution)."""
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * cov + SSIM_C2)
    den = (mu_x**2 + mu_y**2 + SSIM_C1) * (var_x + var_y + SSIM_C2)
    return (num / den).mean()


def covered(alpha: Tensor) -> Tensor:  # [H, W] -> [H, W] bool
    """Pixels where a method drew something: accumulated opacity >= ``COVERAGE_THRESHOLD``."""
    return alpha >= COVERAGE_THRESHOLD


def coverage(alpha: Tensor) -> float:  # [H, W] -> fraction of covered pixels in [0, 1]
    return float(covered(alpha).double().mean())


def coverage_ceiling(
    alpha: Tensor,  # [H, W] accumulated opacity
    target: Tensor,  # [H, W, C] in [0, 1]
    shown: Tensor | None = None,  # [H, W] bool: pixels the render shows in full colour (default: the covered ones)
) -> float:
    """All-pixel PSNR of an image that is exact on the ``shown`` pixels and black elsewhere: the
    best all-pixel PSNR (black background) better colours can give with this drawing. A composited
    render shows the covered pixels (faint drawing below the coverage threshold can add a little);
    a normalised one (`rendering.render`) shows every drawn pixel, alpha > 0, in full colour.

    Example:
        >>> import torch
        >>> alpha = torch.tensor([[1.0, 0.0]])  # one pixel covered, one not
        >>> round(coverage_ceiling(alpha, torch.full((1, 2, 3), 0.1)), 2)  # MSE (0 + 0.01) / 2
        23.01
    """
    if alpha.shape != target.shape[:2]:
        raise ValueError(f"alpha: expected shape {list(target.shape[:2])} (the target's image), got {list(alpha.shape)}")
    if shown is None:
        shown = covered(alpha)
    elif shown.shape != alpha.shape or shown.dtype != torch.bool:
        raise ValueError(f"shown: expected a bool mask of shape {list(alpha.shape)}, got {shown.dtype} {list(shown.shape)}")
    return psnr(torch.where(shown[..., None], target, torch.zeros_like(target)), target)


def depth_agreement(
    depth: Tensor,  # [H, W] rendered z-depth, 0 = nothing drawn
    alpha: Tensor,  # [H, W] accumulated opacity
    sensor: Tensor,  # [H, W] measured z-depth of the target frame, 0 = missing
    tolerance: float,
) -> float:
    """Share of covered pixels with a sensor depth whose rendered depth is within ``tolerance`` of
    it (a floater / misplaced-surface measure); ``nan`` when no pixel qualifies."""
    if depth.shape != alpha.shape or sensor.shape != alpha.shape:
        raise ValueError(f"depth: expected depth, alpha and sensor of one shape, got {list(depth.shape)}, "
                         f"{list(alpha.shape)}, {list(sensor.shape)}")
    mask = covered(alpha) & (sensor > 0)
    if not bool(mask.any()):
        return math.nan
    return float(((depth[mask] - sensor[mask]).abs() <= tolerance).double().mean())


def depth_edge_band(
    depth: Tensor,  # [H, W] sensor z-depth, 0 = missing
    jump: float = EDGE_JUMP,
    radius: int = EDGE_RADIUS,
) -> Tensor:  # [H, W] bool
    """Pixels within ``radius`` pixels (a square window) of a depth edge: a missing depth, or a jump
    to a 4-neighbour over ``jump`` times the nearer of the two depths.

    Renders go wrong there first (mixed "flying" pixels, colour out of register with depth, the
    background's colour on the foreground's rim), so PSNR on these pixels and on the rest ("flat")
    tells edge speckle from noisy surfaces.

    Example:
        >>> import torch
        >>> depth = torch.ones(1, 12)
        >>> depth[:, 6:] = 2.0  # a step between columns 5 and 6
        >>> depth_edge_band(depth, radius=1).int().tolist()
        [[0, 0, 0, 0, 1, 1, 1, 1, 0, 0, 0, 0]]
    """
    if not isinstance(depth, Tensor) or depth.ndim != 2:
        raise ValueError(f"depth: expected a depth map [H, W], got {list(depth.shape) if isinstance(depth, Tensor) else type(depth).__name__}")
    if not (jump > 0 and isinstance(radius, int) and radius >= 0):
        raise ValueError(f"jump, radius: expected a positive jump and a non-negative integer radius, got {jump!r}, {radius!r}")
    d = depth.double()
    edge = d <= 0
    # jumps between valid pixels only: holes are edges themselves, and a hole's 0 would mark its
    # neighbours too (any difference from 0 is a jump)
    across = ~edge[:, :-1] & ~edge[:, 1:] & ((d[:, :-1] - d[:, 1:]).abs() > jump * torch.minimum(d[:, :-1], d[:, 1:]))
    down = ~edge[:-1] & ~edge[1:] & ((d[:-1] - d[1:]).abs() > jump * torch.minimum(d[:-1], d[1:]))
    edge[:, :-1] |= across
    edge[:, 1:] |= across
    edge[:-1] |= down
    edge[1:] |= down
    k = 2 * radius + 1
    return torch.nn.functional.max_pool2d(edge[None, None].float(), k, stride=1, padding=radius)[0, 0] > 0


def cosine_map(a: Tensor, b: Tensor, eps: float = 1e-12) -> Tensor:  # [H, W, C] x2 -> [H, W]
    """Per-pixel cosine similarity of two feature maps (0 where either vector is zero)."""
    _check_pair(a, b)
    a, b = a.double(), b.double()
    return (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(eps)
