import re

import numpy as np
import pytest
import torch

from canonical_core.calibration import quaternion_to_matrix
from canonical_core.decode import GaussianDecoder, symmetric_eigh3, symmetric_eigh3_reference

from ..conftest import folded_scene


def random_covariances(n: int, seed: int = 0) -> torch.Tensor:  # [n, 3, 3] float64, of every kind the decoder meets
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    cov = X @ X.transpose(1, 2)  # generic positive definite
    k = n // 8
    cov[:k] = torch.diag_embed(torch.rand(k, 3, generator=g, dtype=torch.float64))  # already diagonal
    cov[k:2 * k] = 2.0 * torch.eye(3, dtype=torch.float64)  # isotropic: any basis is an eigenbasis
    cov[2 * k:3 * k] = 0.0  # a single observation
    u = torch.randn(k, 3, generator=g, dtype=torch.float64)
    cov[3 * k:4 * k] = u[:, :, None] * u[:, None, :]  # rank 1: points on a line
    a, b = torch.randn(k, 3, generator=g, dtype=torch.float64), torch.randn(k, 3, generator=g, dtype=torch.float64)
    cov[4 * k:5 * k] = a[:, :, None] * a[:, None, :] + b[:, :, None] * b[:, None, :]  # rank 2: points on a plane
    cov[5 * k:6 * k] *= 1e-10  # tiny, as covariances in metres of millimetre voxels are
    return cov


def test_fast_path_matches_the_reference_decomposition():
    cov = random_covariances(4000)
    w_ref, v_ref = symmetric_eigh3_reference(cov)
    w, v = symmetric_eigh3(cov)
    assert w.dtype == v.dtype == torch.float64 and w.shape == (4000, 3) and v.shape == (4000, 3, 3)
    scale = cov.abs().amax((1, 2)).clamp_min(1e-300)[:, None]
    assert ((w - w_ref).abs() / scale).max() < 1e-12
    assert (w[:, 1:] >= w[:, :-1]).all()  # ascending, as the decoder's "axis 0 is the normal" needs
    eye = torch.eye(3, dtype=torch.float64)
    assert (v.transpose(1, 2) @ v - eye).abs().max() < 1e-12
    rebuilt = v @ torch.diag_embed(w) @ v.transpose(1, 2)
    assert ((rebuilt - cov).abs().amax((1, 2)) / scale[:, 0]).max() < 1e-12
    # where the eigenvalues are well apart, each eigenvector is the reference's up to its sign
    gap = torch.minimum(w_ref[:, 1] - w_ref[:, 0], w_ref[:, 2] - w_ref[:, 1]) / scale[:, 0]
    apart = gap > 1e-3
    assert apart.sum() > 1000
    assert ((v[apart] * v_ref[apart]).sum(1).abs() - 1).abs().max() < 1e-8


def test_a_matrix_decomposes_to_the_same_bits_whatever_shares_its_lanes():
    # matrices go through the kernel side by side; a voxel's Gaussian must not depend on which other
    # voxels a decode takes with it (a decode after a fold, from scratch, a level of detail)
    cov = random_covariances(400, seed=2)
    w, v = symmetric_eigh3(cov)
    order = torch.randperm(400, generator=torch.Generator().manual_seed(3))
    w_shuffled, v_shuffled = symmetric_eigh3(cov[order])
    assert torch.equal(w_shuffled, w[order]) and torch.equal(v_shuffled, v[order])
    for i in (0, 57, 399):
        w_alone, v_alone = symmetric_eigh3(cov[i:i + 1])
        assert torch.equal(w_alone[0], w[i]) and torch.equal(v_alone[0], v[i])


def test_symmetric_part_is_used_and_empty_input_is_fine():
    cov = random_covariances(64, seed=1)
    skew = torch.randn(64, 3, 3, dtype=torch.float64)
    w, _ = symmetric_eigh3(cov + (skew - skew.transpose(1, 2)))  # a skew part changes nothing
    assert torch.allclose(w, symmetric_eigh3_reference(cov)[0], rtol=0, atol=1e-9)
    w, v = symmetric_eigh3(torch.zeros(0, 3, 3))
    assert w.shape == (0, 3) and v.shape == (0, 3, 3)


@pytest.mark.parametrize("bad", [torch.zeros(3, 3), torch.zeros(5, 2, 2), torch.zeros(4, 3, 4)])
def test_wrong_shapes_are_refused_with_the_shape(bad):
    for fn in (symmetric_eigh3, symmetric_eigh3_reference):
        with pytest.raises(ValueError, match=re.escape(f"cov: expected a [N, 3, 3] tensor, got {list(bad.shape)}")):
            fn(bad)


def covariances_of(g) -> np.ndarray:  # [N, 3, 3] R diag(s^2) R^T of decoded Gaussians
    R = quaternion_to_matrix(g.quats.detach().double().numpy())
    s = g.scales.detach().double().numpy()
    return R @ (s[:, :, None] ** 2 * np.transpose(R, (0, 2, 1)))


@pytest.mark.realdata
def test_decoder_gives_the_same_gaussians_on_either_path(shelf_frames):
    # the service decodes with the numba path; a training step that needs gradients through the
    # fields takes the reference: the covariances they decode agree on the real capture
    fields = folded_scene(shelf_frames[:3], 0.004).fields()
    decoder = GaussianDecoder(feature_dim=fields["features"].shape[1])
    with torch.no_grad():
        fast = decoder(fields, 0.004)
    cov = fields["position_cov"].clone().requires_grad_(True)
    traced = decoder({**fields, "position_cov": cov}, 0.004)
    assert len(fast) == len(traced) > 10000
    traced.scales.sum().backward()  # the gradient reaches the fields on the reference path
    assert cov.grad is not None  # (the fast path detaches: no gradient would arrive)
    # where a voxel's points lie on a line its two thin axes are any pair about it, and which of them the
    # clamps make thin is up to each eigen solver: compared where the thinnest axis is determined
    spread = torch.linalg.eigvalsh(fields["position_cov"].double())
    determined = (spread[:, 1] - spread[:, 0] > 1e-6 * spread[:, 2]).numpy()
    assert determined.mean() > 0.95
    a, b = covariances_of(fast)[determined], covariances_of(traced)[determined]
    assert np.abs(a - b).max() < 1e-4 * np.abs(b).max()
    assert torch.allclose(fast.scales, traced.scales.detach(), rtol=1e-5, atol=1e-9)
