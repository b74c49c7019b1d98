"""Metrics: PSNR (all pixels / masked), SSIM against hand-checked values and a brute-force reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from canonical_core.eval.metrics import (SSIM_C1, SSIM_C2, cosine_map, coverage, coverage_ceiling, covered, depth_agreement,
                                        depth_edge_band, psnr, ssim)


def test_identical_images_give_infinite_psnr_and_unit_ssim():
    img = torch.rand(32, 40, 3, generator=torch.Generator().manual_seed(0))
    assert psnr(img, img) == math.inf
    assert psnr(img, img, torch.ones(32, 40, dtype=torch.bool)) == math.inf
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)


def test_psnr_of_a_constant_offset_and_of_a_mask():
    a = torch.zeros(8, 8, 3)
    b = a.clone()
    b[:4] = 0.1  # half the pixels off by 0.1 -> MSE 0.005 over all, 0.01 over the top half
    assert psnr(b, a) == pytest.approx(-10 * math.log10(0.005))
    top = torch.zeros(8, 8, dtype=torch.bool)
    top[:4] = True
    assert psnr(b, a, top) == pytest.approx(20.0)
    assert psnr(b, a, ~top) == math.inf
    assert math.isnan(psnr(b, a, torch.zeros(8, 8, dtype=torch.bool)))


def test_ssim_of_two_constant_images_is_the_luminance_term():
    # flat images: sigma_x = sigma_y = sigma_xy = 0, so SSIM = (2 mx my + C1) / (mx^2 + my^2 + C1)
    # = (2 * 0.5 * 0.25 + 1e-4) / (0.25 + 0.0625 + 1e-4) = 0.2501 / 0.3126 = 0.800064 (by hand)
    x = torch.full((20, 20, 3), 0.5)
    y = torch.full((20, 20, 3), 0.25)
    assert SSIM_C1 == pytest.approx(1e-4) and SSIM_C2 == pytest.approx(9e-4)
    assert ssim(x, y) == pytest.approx(0.2501 / 0.3126, abs=1e-9)
    assert ssim(x, y) == pytest.approx(0.800064, abs=1e-6)


def _ssim_brute_force(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. 2004 written out: every valid 11x11 window, Gaussian weights (sigma 1.5)."""
    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    win = np.outer(g, g) / np.outer(g, g).sum()
    values = []
    for c in range(x.shape[2]):
        for i in range(x.shape[0] - 10):
            for j in range(x.shape[1] - 10):
                a, b = x[i:i + 11, j:j + 11, c], y[i:i + 11, j:j + 11, c]
                ma, mb = (win * a).sum(), (win * b).sum()
                va, vb = (win * (a - ma) ** 2).sum(), (win * (b - mb) ** 2).sum()
                cov = (win * (a - ma) * (b - mb)).sum()
                values.append((2 * ma * mb + 1e-4) * (2 * cov + 9e-4) / ((ma**2 + mb**2 + 1e-4) * (va + vb + 9e-4)))
    return float(np.mean(values))


def test_ssim_matches_a_brute_force_window_loop():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (15, 17, 2))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert ssim(torch.from_numpy(x), torch.from_numpy(y)) == pytest.approx(_ssim_brute_force(x, y), abs=1e-9)


def test_metric_arguments_are_checked():
    with pytest.raises(ValueError, match="pred"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="target"):
        ssim(torch.zeros(12, 12, 3), torch.zeros(12, 12))
    with pytest.raises(ValueError, match="mask"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.ones(4, 4))
    with pytest.raises(ValueError, match="11x11"):
        ssim(torch.zeros(8, 30, 3), torch.zeros(8, 30, 3))


def test_coverage_and_cosine():
    alpha = torch.tensor([[0.0, 0.49], [0.5, 1.0]])
    assert covered(alpha).tolist() == [[False, False], [True, True]]
    assert coverage(alpha) == 0.5
    a = torch.tensor([[[1.0, 0.0], [1.0, 1.0]]])
    b = torch.tensor([[[2.0, 0.0], [-1.0, -1.0]]])
    assert cosine_map(a, b)[0].tolist() == pytest.approx([1.0, -1.0])


def test_coverage_ceiling_is_the_psnr_of_exact_covered_pixels_on_black():
    target = torch.rand(8, 10, 3, generator=torch.Generator().manual_seed(0))
    alpha = torch.zeros(8, 10)
    alpha[:, :6] = 0.7  # left 6 columns covered
    uncovered = target[:, 6:]
    expected = -10 * math.log10(float((uncovered.double() ** 2).sum()) / target.numel())
    assert coverage_ceiling(alpha, target) == pytest.approx(expected, rel=1e-9)
    # any colours on the covered pixels with black elsewhere score at most the ceiling
    guess = torch.where(covered(alpha)[..., None], torch.rand(8, 10, 3), torch.zeros(8, 10, 3))
    assert psnr(guess, target) < coverage_ceiling(alpha, target)
    assert coverage_ceiling(torch.ones(8, 10), target) == math.inf  # everything covered: no bound
    with pytest.raises(ValueError, match=r"alpha: expected shape \[8, 10\]"):
        coverage_ceiling(torch.ones(4, 10), target)
    # a normalised render shows every drawn pixel in full colour: its ceiling counts them all
    alpha[:, 6:8] = 0.2  # drawn, not covered
    drawn = alpha > 0
    shown_expected = -10 * math.log10(float((target[:, 8:].double() ** 2).sum()) / target.numel())
    assert coverage_ceiling(alpha, target, drawn) == pytest.approx(shown_expected, rel=1e-9)
    assert coverage_ceiling(alpha, target, drawn) > coverage_ceiling(alpha, target)
    with pytest.raises(ValueError, match=r"shown: expected a bool mask of shape \[8, 10\]"):
        coverage_ceiling(alpha, target, alpha)


def test_depth_agreement_counts_covered_pixels_with_sensor_depth():
    alpha = torch.tensor([[1.0, 1.0, 1.0, 0.0]])
    sensor = torch.tensor([[1.0, 1.0, 0.0, 1.0]])  # third pixel: no sensor depth
    depth = torch.tensor([[1.005, 1.2, 5.0, 1.0]])  # fourth pixel: not covered
    assert depth_agreement(depth, alpha, sensor, tolerance=0.01) == 0.5
    assert math.isnan(depth_agreement(depth, torch.zeros(1, 4), sensor, 0.01))
    with pytest.raises(ValueError, match="depth"):
        depth_agreement(depth, alpha, sensor[:, :3], 0.01)


def test_the_depth_edge_band_marks_pixels_near_a_jump_or_a_hole_and_nothing_on_a_slanted_plane():
    # a plane slanted along u (1 % a column: no jump), a box 20 % nearer in rows 10-19, cols 20-29,
    # and a hole at (30, 50)
    depth = 1.0 + 0.01 * torch.arange(64, dtype=torch.float32)[None].repeat(40, 1)
    assert not depth_edge_band(depth).any()
    depth[10:20, 20:30] *= 0.8
    depth[30, 50] = 0.0
    edges = depth_edge_band(depth)
    expected = torch.zeros(40, 64, dtype=torch.bool)
    expected[10 - 4:20 + 4, 20 - 4:30 + 4] = True  # both sides of the box's rim, and 3 pixels out
    for v, u in ((6, 16), (6, 33), (23, 16), (23, 33)):  # but the box's corners: a jump is to a 4-neighbour
        expected[v, u] = False
    expected[10 + 4:20 - 4, 20 + 4:30 - 4] = False  # the box's inside, more than 3 pixels from its rim
    expected[30 - 3:30 + 4, 50 - 3:50 + 4] = True  # the hole and 3 pixels around it
    assert torch.equal(edges, expected)
    # a jump of 4 % is no edge, one of 6 % is (of the nearer depth)
    step = torch.ones(8, 16)
    step[:, 8:] = 1.04
    assert not depth_edge_band(step).any()
    step[:, 8:] = 1.06
    assert depth_edge_band(step)[0].int().tolist() == [0] * 4 + [1] * 8 + [0] * 4
    with pytest.raises(ValueError, match="depth"):
        depth_edge_band(torch.ones(4))
    with pytest.raises(ValueError, match="radius"):
        depth_edge_band(depth, radius=-1)
