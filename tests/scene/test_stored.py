"""The voxel records' storage: float16 conversions in the kernels round as numpy does, sums are stored
as bounded means and central moments, and earlier snapshots' float32 sums are stored as a fold stores them."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.rendering.sh import sh_basis
from canonical_core.scene.fields import solve_sh, sums_from_stored
from canonical_core.scene.half import converts_in_hardware, floats_of, halves_of, integer_from_half, integer_to_half
from canonical_core.scene.voxel_map import VoxelMap

REPO = Path(__file__).resolve().parents[2]


@numba.njit
def integer_halves(x, out):  # `halves_of` through the integer conversion every CPU has
    for i in range(x.shape[0]):
        out[i] = integer_to_half(x[i])


@numba.njit
def integer_floats(h, out):
    for i in range(h.shape[0]):
        out[i] = integer_from_half(h[i])


@pytest.mark.parametrize("convert", ["in use", "integer"])
def test_halves_round_as_numpy_does_everywhere(convert):
    halves, floats = (halves_of, floats_of) if convert == "in use" else (integer_halves, integer_floats)
    rng = np.random.default_rng(0)
    bits = rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32)
    # around each threshold of the conversion: infinity, normal, subnormal, zero; and exact ties
    edges = np.array([0x477FF000, 0x38800000, 0x33000000, 0x33800000, 0x3F800000, 0x3F801000, 0x38000000], np.int64)
    near = (edges[:, None] + np.arange(-300, 300)[None]).ravel().astype(np.uint32)
    bits = np.concatenate([bits, near, near | np.uint32(0x80000000)])
    x = bits.view(np.float32)
    out = np.empty(len(x), np.uint16)
    halves(x, out)
    with np.errstate(over="ignore"):
        expected = x.astype(np.float16)
    nan = np.isnan(x)
    np.testing.assert_array_equal(out[~nan], expected.view(np.uint16)[~nan])
    assert np.isnan(out[nan].view(np.float16)).all()
    every = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16)
    back = np.empty(len(every), np.float32)
    floats(every, back)
    expected = every.view(np.float16).astype(np.float32)
    finite = ~np.isnan(expected)
    np.testing.assert_array_equal(back.view(np.uint32)[finite], expected.view(np.uint32)[finite])
    assert np.isnan(back[~finite]).all()


def test_the_cpu_converts_half_precision_where_llvm_has_its_instructions():
    assert converts_in_hardware("x86_64", "+sse2,+f16c,+avx") and converts_in_hardware("aarch64", "")
    assert not converts_in_hardware("x86_64", "+sse2,-f16c") and not converts_in_hardware("ppc64le", "+f16c")


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="numba's generic x86-64 target")
def test_kernels_built_for_a_generic_cpu_take_the_integer_conversions(tmp_path):
    # a cache shared between machines is built for NUMBA_CPU_NAME=generic, whose x86-64 has no F16C:
    # LLVM's half conversions would then call functions numba's JIT lacks (the process crashed)
    code = ("import numpy as np\n"
            "from canonical_core.scene.half import HARDWARE, floats_of, halves_of\n"
            "h = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16); x = np.empty(len(h), np.float32)\n"
            "floats_of(h, x); finite = np.isfinite(x); back = np.empty(len(h), np.uint16); halves_of(x, back)\n"
            "print(HARDWARE, bool((back[finite] == h[finite]).all()))")
    env = os.environ | {"NUMBA_CPU_NAME": "generic", "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.split() == ["False", "True"], (done.returncode, done.stderr[-2000:])


def observed_sums(n: int, scale: float, spread: float, seed: int = 3) -> dict[str, np.ndarray]:
    """The float32 sums of ``n`` voxels of 12 weighted observations each (R_scene ``scale``), as a
    fold makes them: points ``spread`` voxels about a spot 0.4 voxels off the centre, seen from
    directions within a few degrees of one another, their colours changing with the direction."""
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.5, 1.5, (n, 12))
    w *= scale / w.sum(1, keepdims=True)
    x = 0.4 + spread * rng.standard_normal((n, 12, 3))
    d = np.array([0.0, 0.0, 1.0]) + 0.05 * rng.standard_normal((n, 12, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = sh_basis(torch.from_numpy(d.reshape(-1, 3)), 1).double().numpy().reshape(n, 12, 4)
    c = np.clip(0.5 + 3.0 * b[:, :, 1:2] + 0.05 * rng.standard_normal((n, 12, 3)), 0, 1)
    k = np.triu_indices(4)
    sums = {"keys": np.arange(n, dtype=np.int64), "rep_rgb": np.zeros((n, 3), np.uint8), "free": np.zeros(n),
            "n_obs": np.full(n, 12, np.int32), "rep_r": np.ones(n), "rep_pos": x[:, 0], "rep_f": np.zeros((n, 4)),
            "r_sum": w.sum(1), "f_sum": np.einsum("vm,vmf->vf", w, rng.uniform(-1, 1, (n, 12, 4))), "rgb_sum": np.einsum("vm,vmc->vc", w, c),
            "pos_sum": np.einsum("vm,vmi->vi", w, x),
            "pos_sq": np.einsum("vm,vmi,vmj->vij", w, x, x)[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]],
            "sh_a": np.einsum("vm,vmi,vmj->vij", w, b, b)[:, k[0][1:], k[1][1:]],
            "sh_b": np.einsum("vm,vmi,vmc->vic", w, b[:, :, 1:], c - 0.5).reshape(n, 9)}
    return {name: v if v.dtype.kind in "iu" else v.astype(np.float32) for name, v in sums.items()}


def loaded(sums: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``sums`` stored by a map (as an earlier snapshot's float32 sums are on loading) and read back."""
    voxels = VoxelMap(feature_dim=4, sh_degree=1, initial_capacity=16)
    voxels.load_sums(sums)
    return voxels.sums()


def covariance(sums: dict[str, torch.Tensor]) -> torch.Tensor:  # [V, 6] E[x x^T] - E[x] E[x]^T, float64
    r = sums["r_sum"].double()[:, None]
    mean = sums["pos_sum"].double() / r
    return sums["pos_sq"].double() / r - mean[:, [0, 0, 0, 1, 1, 2]] * mean[:, [0, 1, 2, 1, 2, 2]]


def test_float32_sums_past_float16s_range_are_stored_as_means_and_central_moments_and_come_back_as_sums():
    sums = observed_sums(64, scale=1e6, spread=0.01)  # sums far past 65504, float16's largest
    stored = loaded(sums)
    assert not {"f_sum", "rgb_sum", "pos_sum", "pos_sq", "sh_a", "sh_b"} & set(stored)
    for name in ("f_mean", "rgb_mean", "pos_mean", "pos_cov", "sh_a_central", "sh_b_central"):
        assert stored[name].dtype == np.float16 and np.isfinite(stored[name].astype(np.float32)).all(), name
    assert stored["rep_dir"].dtype == np.int8 and "rep_f" not in stored
    assert stored["r_sum"].dtype == np.float32
    back = sums_from_stored({k: torch.as_tensor(v) for k, v in stored.items()})
    for name in ("rgb_sum", "pos_sum"):  # float16's rounding of each mean, times R_scene
        np.testing.assert_allclose(back[name].numpy(), sums[name], rtol=1e-3, err_msg=name)
    # the spread of 0.01 voxels is 2.5e-4 of the raw second moment (0.16): float16's rounding of that
    # would leave nothing of it; stored as a central moment it keeps float16's relative precision
    true = covariance({k: torch.as_tensor(v) for k, v in sums.items()})
    diagonal = [0, 3, 5]
    assert torch.allclose(covariance(back)[:, diagonal], true[:, diagonal], rtol=5e-3)
    raw_half = {name: torch.as_tensor((sums[name] / sums["r_sum"][:, None]).astype(np.float16).astype(np.float32)
                                      * sums["r_sum"][:, None]) for name in ("pos_sum", "pos_sq")}
    assert not torch.allclose(covariance(raw_half | {"r_sum": torch.as_tensor(sums["r_sum"])})[:, diagonal],
                              true[:, diagonal], rtol=0.5)


def test_a_nonpositive_r_scene_stores_zero_moments():
    sums = observed_sums(4, scale=2.0, spread=0.05)
    sums["r_sum"][0] = 0.0
    stored = loaded(sums)
    for name in ("f_mean", "rgb_mean", "pos_mean", "pos_cov", "sh_a_central", "sh_b_central"):
        assert not stored[name][0].any() and stored[name][1:].any(), name


def test_the_sh_fit_from_stored_moments_keeps_a_narrow_cone_of_views_where_raw_float16_would_not():
    # directions within a few degrees: the view-dependent terms are a small difference of raw moments
    sums = observed_sums(200, scale=3.0, spread=0.05, seed=5)
    back = sums_from_stored({k: torch.as_tensor(v) for k, v in loaded(sums).items()})

    def fit(s):
        return solve_sh(torch.as_tensor(s["r_sum"]), torch.as_tensor(s["rgb_sum"]), torch.as_tensor(s["sh_a"]),
                        torch.as_tensor(s["sh_b"]), 0.003)

    exact = fit(sums)
    stored_err = (fit(back) - exact).abs().max()
    r = sums["r_sum"][:, None]
    raw_half = sums | {name: (sums[name] / r).astype(np.float16).astype(np.float32) * r
                       for name in ("rgb_sum", "sh_a", "sh_b")}
    raw_err = (fit(raw_half) - exact).abs().max()
    assert stored_err < 0.01 and raw_err > 10 * stored_err, (stored_err, raw_err)


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


@pytest.mark.parametrize("channels", [16, 3])
def test_the_representative_is_stored_as_its_8_bit_direction(channels):
    rng = np.random.default_rng(1)
    features = rng.standard_normal((500, channels)).astype(np.float32) * rng.uniform(0.01, 100, (500, 1)).astype(np.float32)
    features[0] = 0.0  # no direction: stays zero
    voxels = VoxelMap(feature_dim=channels, sh_degree=1, initial_capacity=16)
    sums = observed_sums(500, scale=2.0, spread=0.05)
    voxels.load_sums({k: v for k, v in sums.items() if k != "f_sum"} | {"rep_f": features, "f_sum": features})
    direction = voxels.sums()["rep_dir"]
    assert direction.shape == (500, channels) and direction.dtype == np.int8 and not direction[0].any()
    assert (np.abs(direction[1:]).max(axis=1) == 127).all()  # the whole int8 range for every direction
    back = sums_from_stored({k: torch.as_tensor(v) for k, v in voxels.sums().items()})["rep_f"].double()
    exact = torch.from_numpy(features).double()
    cos = torch.nn.functional.cosine_similarity(back[1:], exact[1:], dim=-1)
    assert cos.min() > 0.999
    # a cosine between two stored directions moves by a hundredth at most against the exact one
    others = torch.from_numpy(rng.standard_normal((500, channels))).double()
    moved = (torch.nn.functional.cosine_similarity(back[1:], others[1:], dim=-1)
             - torch.nn.functional.cosine_similarity(exact[1:], others[1:], dim=-1)).abs()
    assert moved.max() < 0.01
