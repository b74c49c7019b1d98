"""The voxel records' storage: float16 conversions in the kernels round as numpy does, sums are stored
as bounded means, and earlier snapshots' float32 sums are stored as a fold stores them."""

from __future__ import annotations

import numpy as np
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.scene.fields import sums_from_means
from canonical_core.scene.half import floats_of, halves_of
from canonical_core.scene.voxel_map import VoxelMap


def test_halves_round_as_numpy_does_everywhere():
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32)
    # around each threshold of the conversion: infinity, normal, subnormal, zero; and exact ties
    edges = np.array([0x477FF000, 0x38800000, 0x33000000, 0x33800000, 0x3F800000, 0x3F801000, 0x38000000], np.int64)
    near = (edges[:, None] + np.arange(-300, 300)[None]).ravel().astype(np.uint32)
    bits = np.concatenate([bits, near, near | np.uint32(0x80000000)])
    x = bits.view(np.float32)
    out = np.empty(len(x), np.uint16)
    halves_of(x, out)
    with np.errstate(over="ignore"):
        expected = x.astype(np.float16)
    nan = np.isnan(x)
    np.testing.assert_array_equal(out[~nan], expected.view(np.uint16)[~nan])
    assert np.isnan(out[nan].view(np.float16)).all()
    every = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16)
    back = np.empty(len(every), np.float32)
    floats_of(every, back)
    expected = every.view(np.float16).astype(np.float32)
    finite = ~np.isnan(expected)
    np.testing.assert_array_equal(back.view(np.uint32)[finite], expected.view(np.uint32)[finite])
    assert np.isnan(back[~finite]).all()


def float32_sums(voxels: VoxelMap, n: int, scale: float) -> dict[str, np.ndarray]:
    """Sums as an earlier snapshot holds them (float32 sums, no means), R_scene ``scale`` times the inputs'."""
    rng = np.random.default_rng(3)
    sums = {"keys": np.arange(n, dtype=np.int64), "rep_rgb": np.zeros((n, 3), np.uint8),
            "free": np.zeros(n, np.float32), "n_obs": np.ones(n, np.int32)}
    for name, (first, shape) in voxels.layout.columns.items():
        sums[name] = rng.uniform(-1, 1, (n, *shape)).astype(np.float32)
    sums["r_sum"] = np.full(n, scale, np.float32)
    sums["r_sum"][0] = 0.0  # no weight: its means are stored as 0
    for name in ("f_sum", "sh_a", "sh_b"):
        sums[name] *= np.float32(scale)
        sums[name][0] = 0.0
    return sums


def test_float32_sums_past_float16s_range_are_stored_as_means_and_come_back_as_sums():
    voxels = VoxelMap(feature_dim=4, sh_degree=1, initial_capacity=16)
    sums = float32_sums(voxels, 8, scale=1e6)  # sums far past 65504, float16's largest
    voxels.load_sums(sums)
    stored = voxels.sums()
    assert "f_sum" not in stored and stored["f_mean"].dtype == np.float16
    assert np.isfinite(stored["f_mean"].astype(np.float32)).all()
    assert not stored["f_mean"][0].any()
    back = sums_from_means({k: torch.as_tensor(v) for k, v in stored.items()})
    for name in ("f_sum", "rep_f"):  # float16's rounding of each mean, times R_scene
        np.testing.assert_allclose(back[name].numpy(), sums[name], rtol=1e-3, atol=1e-3 * np.abs(sums[name]).max(),
                                   err_msg=name)
    for name in ("r_sum", "rgb_sum", "pos_sq", "sh_a", "sh_b"):  # float32 fields as they were
        np.testing.assert_array_equal(stored[name], sums[name], err_msg=name)


def test_a_snapshot_stores_the_records_as_they_are_and_loads_them_bit_for_bit(shelf_frames):
    scene = Scene(SceneConfig(voxel_size=0.01))
    for frame in shelf_frames[:3]:
        scene.fold(frame)
    again = Scene.from_bytes(scene.to_bytes())
    assert again.digest() == scene.digest()
    a, b = scene.sums(), again.sums()
    assert a["f_mean"].dtype == np.float16 and a["r_sum"].dtype == np.float32
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    scene.fold(shelf_frames[3])
    again.fold(shelf_frames[3])
    assert again.digest() == scene.digest()
