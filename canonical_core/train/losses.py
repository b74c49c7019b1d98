"""The render loss of training: MSE plus a differentiable SSIM, on a held-out frame.

SSIM uses the evaluation's window and constants (`eval.metrics`: an 11-tap Gaussian of std 1.5,
C1 = 0.01^2, C2 = 0.03^2) over the valid part of the image, so ``1 - ssim_loss`` of two images is
the evaluation's `eval.metrics.ssim` of them up to float rounding.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..eval.metrics import SSIM_SIGMA, SSIM_WINDOW, _gaussian_window, mean_ssim

SSIM_WEIGHT = 0.02  # weight of (1 - SSIM) next to the MSE: small, so that PSNR (what the evaluation scores) leads the loss


def ssim_torch(
    pred: Tensor,  # [H, W, C] in [0, 1]
    target: Tensor,  # [H, W, C] in [0, 1]
) -> Tensor:  # [] mean SSIM, differentiable in pred
    """Mean structural similarity over the valid windows (Wang et al. 2004)."""
    if pred.shape != target.shape or pred.ndim != 3:
        raise ValueError(f"pred: expected [H, W, C] like target {list(target.shape)}, got {list(pred.shape)}")
    if min(pred.shape[:2]) < SSIM_WINDOW:
        raise ValueError(f"pred: SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {list(pred.shape[:2])}")
    c = pred.shape[2]
    g = _gaussian_window(SSIM_WINDOW, SSIM_SIGMA).to(pred)
    kernel = (g[:, None] * g[None, :]).expand(c, 1, SSIM_WINDOW, SSIM_WINDOW)

    def blur(t: Tensor) -> Tensor:  # [1, C, H, W] -> [1, C, H - 10, W - 10]
        return torch.nn.functional.conv2d(t, kernel, groups=c)

    return mean_ssim(pred.permute(2, 0, 1)[None], target.to(pred).permute(2, 0, 1)[None], blur)


def render_loss(
    pred: Tensor,  # [H, W, 3] rendered colour in [0, 1]
    target: Tensor,  # [H, W, 3] the held-out frame's colour in [0, 1]
    ssim_weight: float = SSIM_WEIGHT,
) -> Tensor:  # [] scalar
    """MSE + ``ssim_weight`` (1 - SSIM) over all pixels."""
    target = target.to(pred)
    return torch.mean((pred - target) ** 2) + ssim_weight * (1.0 - ssim_torch(pred, target))


def coverage_loss(
    alpha: Tensor,  # [H, W] or [H, W, 1] rendered opacity in [0, 1]
    measured: Tensor,  # [H, W] bool: pixels where the target frame measured depth (a surface is there)
) -> Tensor:  # [] scalar; 0 where nothing was measured
    """Mean (1 - alpha)^2 over the ``measured`` pixels: a render that leaves a measured surface
    uncovered pays for it, which the normalised colour of `render_loss` does not see."""
    alpha = alpha.reshape(measured.shape)
    if not bool(measured.any()):
        return alpha.sum() * 0.0
    return torch.mean((1.0 - alpha[measured]) ** 2)
