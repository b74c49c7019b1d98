"""Spherical harmonics: an orthonormal real basis (checks every constant) and the 3DGS colour rule."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from canonical_core.gaussians import SH_C0
from canonical_core.rendering.sh import _sh_contract_kernel, sh_basis, sh_basis_at_points, sh_to_rgb, sh_to_rgb_fast


def fibonacci_sphere(n: int) -> torch.Tensor:  # [n, 3] near-uniform unit vectors
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def test_basis_is_orthonormal_over_the_sphere():
    dirs = fibonacci_sphere(40_000)
    basis = sh_basis(dirs, 3)  # [n, 16]
    gram = basis.T @ basis * (4 * math.pi / len(dirs))
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-3)


def test_degree_one_colour_follows_the_view_direction():
    sh = torch.zeros(1, 4, 3)
    sh[0, 0] = 0.2 / SH_C0  # DC: 0.5 + 0.2
    sh[0, 3] = torch.tensor([1.0, 0.0, -1.0])  # the x-linear basis function, -C1 x
    c1 = math.sqrt(3 / (4 * math.pi))
    seen_along_x = sh_to_rgb(sh, torch.tensor([[2.0, 0.0, 0.0]]))[0]  # direction need not be unit
    assert torch.allclose(seen_along_x, torch.tensor([0.7 - c1, 0.7, 0.7 + c1]))
    seen_along_z = sh_to_rgb(sh, torch.tensor([[0.0, 0.0, 1.0]]))[0]
    assert torch.allclose(seen_along_z, torch.tensor([0.7, 0.7, 0.7]))


def test_colour_is_clamped_below_at_zero_only():
    sh = torch.zeros(2, 1, 3)
    sh[0, 0] = -5.0
    sh[1, 0] = 5.0
    rgb = sh_to_rgb(sh, torch.zeros(2, 3))
    assert (rgb[0] == 0).all() and torch.allclose(rgb[1], torch.full((3,), 0.5 + 5 * SH_C0))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_fast_path_equals_the_pytorch_definition(degree):
    rng = np.random.default_rng(degree)
    sh = torch.from_numpy(rng.normal(0, 0.8, (500, (degree + 1) ** 2, 3)).astype(np.float32))  # some clamp at 0
    dirs = torch.from_numpy(rng.normal(0, 3, (500, 3)).astype(np.float32))
    dirs[0] = 0.0  # a mean at the camera centre: DC only
    expected = sh_to_rgb(sh, dirs)
    assert (expected == 0).any()
    assert torch.allclose(sh_to_rgb_fast(sh, dirs), expected, rtol=0, atol=2e-6)
    centre = np.array([0.5, -1.0, 2.0], np.float32)
    unit = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-30)
    basis = sh_basis_at_points(dirs.numpy() + centre, centre, degree)
    assert np.allclose(basis[1:], sh_basis(unit, degree)[1:].numpy(), atol=2e-6)
    assert np.allclose(basis[0, 1:], 0) and basis[0, 0] == np.float32(SH_C0)


def test_fused_degree_one_path_equals_the_general_kernels_bit_for_bit():
    rng = np.random.default_rng(5)
    sh = rng.normal(0, 0.8, (3000, 4, 3)).astype(np.float32)
    points = rng.normal(0, 3, (3000, 3)).astype(np.float32)
    centre = np.array([0.5, -1.0, 2.0], np.float32)
    points[:3] = centre  # means on the viewpoint: DC only
    general = np.empty((3000, 3), np.float32)
    _sh_contract_kernel(sh_basis_at_points(points, centre, 1), sh, general)
    lines = np.zeros((3000, 16), np.float32)  # a strided output, as the renderer's splat lines
    fused = sh_to_rgb_fast(torch.from_numpy(sh), torch.from_numpy(points), centre, out=lines[:, 4:7])
    assert np.array_equal(fused.numpy(), general) and np.array_equal(lines[:, 4:7], general)
    assert not lines[:, :4].any() and not lines[:, 7:].any()


def test_fast_path_rejects_an_unknown_degree():
    with pytest.raises(ValueError, match="degree"):
        sh_basis_at_points(np.zeros((1, 3), np.float32), np.zeros(3, np.float32), 4)
