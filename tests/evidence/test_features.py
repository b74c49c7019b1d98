import numpy as np
import pytest
import torch

from canonical_core.evidence.features import (
    default_features_at, default_features_reference, projection_matrix, sample_client_features)


@pytest.mark.parametrize("seed", [0, 1])
def test_fast_path_equals_reference_including_borders(seed):
    rgb = torch.randint(0, 256, (37, 53, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(seed))
    rows, cols = np.nonzero(np.ones((37, 53), bool))
    fast = default_features_at(rgb.numpy(), rows, cols)
    ref = default_features_reference(rgb)[rows, cols].numpy()
    assert np.abs(fast - ref).max() < 1e-5
    assert np.allclose(np.linalg.norm(fast, axis=1), 1.0, atol=1e-5)


@pytest.mark.realdata
def test_same_surface_point_is_more_similar_than_other_points(shelf_frames):
    """Discriminative on real images: a point seen in two views (frames 4 apart) is more similar
    to itself than to other points of the same view pair."""
    a, b = shelf_frames[10], shelf_frames[14]
    v, u = torch.nonzero(a.depth > 0, as_tuple=True)
    pick = torch.randperm(v.numel(), generator=torch.Generator().manual_seed(0))[:4000]
    v, u = v[pick], u[pick]
    uv, z = b.camera.project(a.camera.lift(torch.stack([u, v], -1).float(), a.depth[v, u]))
    ub, vb = uv[:, 0].round().long(), uv[:, 1].round().long()
    ok = (z > 0) & (ub >= 4) & (ub < b.width - 4) & (vb >= 4) & (vb < b.height - 4)
    ok &= (b.depth[vb.clamp(0, b.height - 1), ub.clamp(0, b.width - 1)] - z).abs() < 0.01  # visible in b
    fa = default_features_at(a.rgb.numpy(), v[ok].numpy(), u[ok].numpy())
    fb = default_features_at(b.rgb.numpy(), vb[ok].numpy(), ub[ok].numpy())
    same = (fa * fb).sum(1)
    other = (fa * np.roll(fb, 97, axis=0)).sum(1)
    assert ok.sum() > 1000
    assert np.median(same) > 0.9
    assert np.median(same) - np.median(other) > 0.3
    assert (same > other).mean() > 0.85


def test_projection_preserves_cosines_when_widening():
    P = projection_matrix(16, 32)
    x = np.random.default_rng(0).standard_normal((10, 16)).astype(np.float32)
    assert np.allclose((x @ P) @ (x @ P).T, x @ x.T, atol=1e-4)
    assert np.array_equal(P, projection_matrix(16, 32))  # fixed: the same in every process


def test_client_features_sampled_at_pixel_centres():
    feats = np.arange(2 * 3, dtype=np.float32).reshape(2, 3, 1)  # half-resolution map of a 4x6 image
    rows, cols = np.nonzero(np.ones((4, 6), bool))
    out = sample_client_features(feats, rows, cols, (4, 6)).reshape(4, 6)
    assert np.array_equal(out, np.repeat(np.repeat(feats[..., 0], 2, 0), 2, 1))
