"""Registration weighting: evidence near depth edges, where colour from a second sensor may belong to
the other surface, is down-weighted; the numba path equals the PyTorch definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.evidence import extract_evidence
from canonical_core.evidence.registration import (depth_edges, edge_distance, registration_weight,
                                                  registration_weight_reference)


def random_depth(rng, shape=(40, 56)) -> np.ndarray:
    valid = rng.random(shape) < 0.8
    steps = np.where(rng.random(shape) < 0.6, 1.0, rng.uniform(0.4, 3.0, shape))
    return (valid * steps).astype(np.float32)


@pytest.mark.parametrize("radius", [0.0, 1.0, 2.5, 4.0, 9.0])
def test_fast_weight_equals_reference(radius):
    rng = np.random.default_rng(int(radius * 10))
    for _ in range(5):
        depth = random_depth(rng)
        rows, cols = np.nonzero(depth > 0)
        fast = registration_weight(depth, rows, cols, radius, 0.01)
        ref = registration_weight_reference(torch.from_numpy(depth), radius, 0.01).numpy()[rows, cols]
        np.testing.assert_array_equal(fast, ref.astype(np.float32))


def test_edge_distance_is_the_chessboard_distance_capped():
    rng = np.random.default_rng(3)
    edges = rng.random((25, 31)) < 0.03
    got = edge_distance(edges, cap=6)
    ev, eu = np.nonzero(edges)
    v, u = np.mgrid[:25, :31]
    brute = np.maximum(np.abs(v[..., None] - ev), np.abs(u[..., None] - eu)).min(-1)
    np.testing.assert_array_equal(got, np.minimum(brute, 6))


def test_a_step_marks_both_sides_and_noise_marks_nothing():
    depth = np.full((12, 20), 1.0, np.float32)
    depth[:, 10:] = 1.5
    edges = depth_edges(depth, voxel_size=0.01)
    assert edges[:, 9:11].all() and edges.sum() == 24
    flat = 1.0 + np.random.default_rng(0).normal(0, 0.002, (12, 20)).astype(np.float32)  # within 3 sigma + 2 voxels
    assert not depth_edges(flat, voxel_size=0.01).any()
    holes = depth.copy()
    holes[:, 10:] = 0  # a hole is not an edge: nothing is known behind it
    assert not depth_edges(holes, voxel_size=0.01).any()


def test_weight_ramps_from_the_edge_and_radius_zero_is_off():
    depth = np.full((8, 30), 1.0, np.float32)
    depth[:, 15:] = 2.0
    rows, cols = np.zeros(30, np.int64), np.arange(30)
    w = registration_weight(depth, rows, cols, 4.0, 0.02)
    distance = np.minimum(np.abs(cols - 14.5) - 0.5, 4)
    np.testing.assert_allclose(w, np.minimum(1.0, (distance + 1) / 5), rtol=1e-6)
    assert (registration_weight(depth, rows, cols, 0.0, 0.02) == 1).all()


def test_extract_evidence_lowers_reliability_only_near_edges():
    H, W = 24, 32
    depth = np.full((H, W), 1.0, np.float32)
    depth[:, 16:] = 1.6
    frame = Frame(rgb=torch.zeros((H, W, 3), dtype=torch.uint8), camera=Camera([[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]], np.eye(4), W, H),
                  depth=torch.from_numpy(depth))
    off = extract_evidence(frame, SceneConfig(voxel_size=0.02))
    on = extract_evidence(frame, SceneConfig(voxel_size=0.02, sensor={"registration_px": 3.0}))
    ratio = on.reliability / off.reliability
    far = np.abs(off.cols - 15.5) > 3  # 3 px or more from the edge pixels (columns 15 and 16)
    np.testing.assert_allclose(ratio[far], 1.0, rtol=1e-6)
    np.testing.assert_allclose(ratio[off.cols == 15], 0.25, rtol=1e-5)
    assert (ratio[~far] < 1).all()

