"""The fused splat-shape kernel (`scene.shapes.voxel_shapes`) against its reference,
`GaussianDecoder.base_shapes` of `fields_from_sums`, on a real capture's sums and on sums built to
be awkward (repeated eigenvalues, flat and degenerate voxels, a reflected eigenbasis)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.decode import GaussianDecoder
from canonical_core.scene.fields import fields_from_sums
from canonical_core.scene.shapes import voxel_shapes


def reference(sums, rows, config, decoder):
    index = torch.from_numpy(rows)
    fields = fields_from_sums({k: torch.as_tensor(v).index_select(0, index) for k, v in sums.items()}, config, sort=False)
    return decoder.base_shapes(fields, config.voxel_size)


def covariance(std, quats):  # [N, 3], [N, 4] wxyz -> [N, 3, 3] = R diag(std^2) R^T
    w, x, y, z = quats.double().unbind(-1)
    R = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)  # fmt: skip
    return R @ torch.diag_embed(std.double() ** 2) @ R.transpose(1, 2)


def assert_shapes_match(sums, rows, config, decoder):
    fast = voxel_shapes(sums, rows, config.voxel_size, config.research.eps, decoder)
    ref = reference(sums, rows, config, decoder)
    for name, a, b in zip(("centroid", "std", "quats"), fast, ref):
        assert a.dtype == torch.float32 and a.shape == b.shape, name
    torch.testing.assert_close(fast[0], ref[0], rtol=0, atol=1e-7)
    torch.testing.assert_close(fast[1], ref[1], rtol=1e-6, atol=1e-7)
    # the same axes up to round-off: the covariances agree (quaternions too, except where two
    # eigenvalues tie and any rotation within their plane is an answer)
    torch.testing.assert_close(covariance(*fast[1:]), covariance(*ref[1:]), rtol=1e-5, atol=1e-7)
    return fast, ref


@pytest.fixture(scope="module")
def scene():
    s = Scene(SceneConfig(voxel_size=0.05))
    for frame in synthetic_rgbd(num_frames=6, width=64, height=48):
        s.fold(frame)
    return s


def test_the_fast_path_equals_the_reference_on_a_folded_scene(scene):
    sums = scene.sums()
    rows = np.arange(len(sums["keys"]), dtype=np.int64)
    fast, ref = assert_shapes_match(sums, rows, scene.config, GaussianDecoder(scene.config.features.dim))
    same = (fast[2] - ref[2]).abs().amax(1) < 1e-5
    assert same.float().mean() > 0.99  # bit-near quaternions almost everywhere


def test_a_subset_of_rows_in_any_order(scene):
    sums = scene.sums()
    rows = np.random.default_rng(0).permutation(len(sums["keys"]))[:50].astype(np.int64)
    assert_shapes_match(sums, rows, scene.config, GaussianDecoder(scene.config.features.dim, min_thickness=0.1, max_extent=0.8))


def test_awkward_voxels(scene):
    """Single-point voxels (zero covariance), exact planes, isotropic spreads and a reflected basis."""
    sums = {k: v[:6].copy() for k, v in scene.sums().items()}
    r = np.float32(2.0)
    sums["r_sum"][:] = r
    local = [(0.5, 0.5, 0.5), (0.1, 0.9, 0.5), (0.5, 0.5, 0.5), (0.2, 0.3, 0.4), (0.5, 0.5, 0.5), (0.9, 0.1, 0.1)]
    # stored as the map stores them (`stored`): the mean and the central second moment over R_scene
    sums["pos_mean"][:] = np.asarray(local, np.float16)
    cov = np.zeros((6, 6), np.float32)
    cov[2] = [0.01, 0, 0, 0.01, 0, 0.01]  # isotropic: every axis ties
    cov[4] = [0.02, 0, 0, 0.02, 0, 0.0]  # a flat disc: two axes tie
    cov[5] = [0.01, -0.004, 0.002, 0.02, 0.003, 0.03]
    sums["pos_cov"][:] = cov
    rows = np.arange(6, dtype=np.int64)
    assert_shapes_match(sums, rows, scene.config, GaussianDecoder(scene.config.features.dim))


def test_no_rows():
    config = SceneConfig(voxel_size=0.05)
    sums = Scene(config).sums()
    centroid, std, quats = voxel_shapes(sums, np.empty(0, np.int64), 0.05, config.research.eps, GaussianDecoder(16))
    assert centroid.shape == (0, 3) and std.shape == (0, 3) and quats.shape == (0, 4)
