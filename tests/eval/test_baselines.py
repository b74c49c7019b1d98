"""Baselines: pixel-aligned discs (footprint, orientation, colour) and per-voxel merging."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, Gaussians
from canonical_core.calibration import quaternion_to_matrix
from canonical_core.decode import GaussianDecoder
from canonical_core.eval.baselines import (
    SPACING_FRACTION,
    THICKNESS,
    full_support_opacity,
    gaussian_merge,
    merge_per_voxel,
    pixel_aligned,
)
from canonical_core.gaussians import rgb_to_sh_dc


def _frame(depth: np.ndarray, c2w=None) -> Frame:
    h, w = depth.shape
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = np.arange(w, dtype=np.uint8)[None] * 10
    cam = Camera(K=[[100, 0, (w - 1) / 2], [0, 50, (h - 1) / 2], [0, 0, 1]], c2w=np.eye(4) if c2w is None else c2w,
                 width=w, height=h)
    return Frame(rgb=rgb, camera=cam, depth=depth.astype(np.float32))


def test_pixel_aligned_discs_face_the_camera_with_the_pixel_footprint():
    depth = np.full((12, 16), 2.0, np.float32)
    depth[0, 0] = 0.0  # one missing pixel
    g = pixel_aligned([_frame(depth)], voxel_size=0.01)
    assert len(g) == 12 * 16 - 1
    inner = (g.means[:, 0].abs() < 0.05) & (g.means[:, 1].abs() < 0.05)  # away from borders and the hole: rho = 1
    assert g.scales[inner, 0] == pytest.approx(torch.full((int(inner.sum()),), SPACING_FRACTION * 2.0 / 100))
    assert g.scales[inner, 1] == pytest.approx(torch.full((int(inner.sum()),), SPACING_FRACTION * 2.0 / 50))
    assert torch.allclose(g.scales[:, 2], THICKNESS * g.scales[:, :2].min(1).values)
    assert torch.allclose(g.quats, torch.tensor([1.0, 0.0, 0.0, 0.0]).expand_as(g.quats))  # identity camera
    assert torch.allclose(g.opacities, torch.full_like(g.opacities, full_support_opacity(GaussianDecoder(16))))
    assert g.features is not None and g.features.shape == (len(g), 16)
    assert torch.allclose(g.colours[:, 0], torch.cat([torch.arange(1, 16), *[torch.arange(16)] * 11]).float() * 10 / 255,
                          atol=1e-6)


def test_sparser_depth_gets_wider_discs():
    dense = pixel_aligned([_frame(np.full((20, 20), 1.0))], 0.01, features=False)
    sparse_depth = np.full((20, 20), 1.0)
    sparse_depth[::2] = 0.0  # every other row missing: rho ~ 1/2 -> std x sqrt(2)
    sparse = pixel_aligned([_frame(sparse_depth)], 0.01, features=False)
    assert sparse.features is None
    assert float(sparse.scales[:, 0].median()) / float(dense.scales[:, 0].median()) == pytest.approx(
        np.sqrt(25 / 15), rel=0.05)  # 5x5 window with 3 or 2 valid rows of 5: median density 15 / 25


def test_rotated_camera_rotates_the_discs():
    R = quaternion_to_matrix(np.array([np.cos(0.3), 0.0, np.sin(0.3), 0.0]))
    c2w = np.eye(4)
    c2w[:3, :3] = R
    g = pixel_aligned([_frame(np.full((4, 4), 1.0), c2w)], 0.01, features=False)
    assert np.allclose(quaternion_to_matrix(g.quats.double().numpy()), R[None], atol=1e-6)


def _gaussians(means, scales, colors, opacities=None, features=None) -> Gaussians:
    n = len(means)
    return Gaussians(means=torch.tensor(means, dtype=torch.float32), scales=torch.tensor(scales, dtype=torch.float32),
                     quats=torch.tensor([[1.0, 0, 0, 0]] * n), opacities=torch.tensor(opacities or [0.5] * n),
                     sh=rgb_to_sh_dc(torch.tensor(colors, dtype=torch.float32))[:, None],
                     features=None if features is None else torch.tensor(features, dtype=torch.float32))


def test_merge_averages_members_and_matches_their_second_moments():
    g = _gaussians(means=[[0.01, 0.02, 0.02], [0.03, 0.02, 0.02], [0.55, 0.5, 0.5]],
                   scales=[[0.001, 0.002, 0.003]] * 3, colors=[[1, 0, 0], [0, 0, 1], [0, 1, 0]],
                   opacities=[0.2, 0.6, 0.9], features=[[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    m = merge_per_voxel(g, voxel_size=0.1)
    assert len(m) == 2
    first = int(torch.argmin(m.means[:, 0]))
    assert m.means[first].tolist() == pytest.approx([0.02, 0.02, 0.02])
    assert m.colours[first].tolist() == pytest.approx([0.5, 0.0, 0.5], abs=1e-6)
    assert float(m.opacities[first]) == pytest.approx(0.4)
    assert m.features[first].tolist() == pytest.approx([0.5, 0.5])
    R = torch.from_numpy(quaternion_to_matrix(m.quats[first].double().numpy()))
    cov = R @ torch.diag(m.scales[first].double() ** 2) @ R.T
    expected = torch.diag(torch.tensor([0.001**2 + 0.01**2, 0.002**2, 0.003**2], dtype=torch.float64))
    assert torch.allclose(cov, expected, atol=1e-9)
    assert torch.linalg.det(R) == pytest.approx(1.0)
    lone = 1 - first  # a voxel with one member keeps it
    assert m.means[lone].tolist() == pytest.approx([0.55, 0.5, 0.5])
    assert sorted(m.scales[lone].tolist()) == pytest.approx([0.001, 0.002, 0.003], rel=1e-4)


def test_gaussian_merge_has_at_most_one_gaussian_per_voxel():
    frames = [_frame(np.full((16, 16), 1.0)), _frame(np.full((16, 16), 1.0))]
    pixels = pixel_aligned(frames, 0.01)
    merged = gaussian_merge(frames, 0.01)
    cells = torch.unique(torch.floor(pixels.means / 0.01), dim=0)
    assert len(merged) == len(cells) < len(pixels)
    with pytest.raises(ValueError, match="voxel_size"):
        merge_per_voxel(pixels, 0.0)
