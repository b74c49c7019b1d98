"""The per-voxel SH solve: the numba fast path held to the PyTorch reference, and what the fit means."""

import re

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.rendering.sh import sh_basis
from canonical_core.scene import Scene
from canonical_core.datasets import load_dataset
from canonical_core.scene.fields import (decoder_fields, fields_from_sums, sh_sum_widths, solve_sh, solve_sh_reference,
                                          sums_from_stored)


def streamed_sums(degree: int, voxels: int, observations: int, seed: int = 0, directions: int | None = None,
                  dtype=torch.float32):
    """The sums the fold streams for ``voxels`` voxels of ``observations`` weighted observations each
    (random directions, weights and colours; ``directions`` distinct directions per voxel if given):
    r [V], color_sum [V, 3], sh_a, sh_b in `sh_sum_widths` layout, and the observations themselves."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    m = directions or observations
    d = torch.nn.functional.normalize(torch.randn(voxels, m, 3, generator=g, dtype=torch.float64), dim=-1)
    d = d.repeat(1, observations // m + 1, 1)[:, :observations]
    b = sh_basis(d.reshape(-1, 3), degree).reshape(voxels, observations, k).double()
    w = torch.rand(voxels, observations, generator=g, dtype=torch.float64) + 0.1
    c = torch.rand(voxels, observations, 3, generator=g, dtype=torch.float64)
    rows, cols = torch.triu_indices(k, k)
    sh_a = torch.einsum("vm,vmi,vmj->vij", w, b, b)[:, rows[1:], cols[1:]]
    sh_b = torch.einsum("vm,vmi,vmc->vic", w, b[:, :, 1:], c - 0.5).reshape(voxels, -1)
    assert (sh_a.shape[1], sh_b.shape[1]) == sh_sum_widths(degree)
    sums = (w.sum(1), (w[:, :, None] * c).sum(1), sh_a, sh_b)
    return tuple(t.to(dtype) for t in sums), (d, w, c)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fast_solve_matches_the_reference(degree, dtype):
    (r, c, sh_a, sh_b), _ = streamed_sums(degree, voxels=500, observations=40, seed=degree, dtype=dtype)
    for regularization in (0.003, 0.3):
        fast = solve_sh(r, c, sh_a, sh_b, regularization)
        ref = solve_sh_reference(r, c, sh_a, sh_b, regularization)
        assert fast.shape == ref.shape == (500, (degree + 1) ** 2, 3) and fast.dtype == torch.float32
        assert torch.allclose(fast, ref, rtol=1e-4, atol=1e-5)


def test_fast_solve_is_the_least_squares_fit_of_the_observations():
    # with a negligible ridge the solve is the weighted least-squares SH fit of the observed colours:
    # its residual is orthogonal to every basis function (the normal equations hold)
    (r, c, sh_a, sh_b), (d, w, colours) = streamed_sums(1, voxels=50, observations=30, seed=3, dtype=torch.float64)
    sh = solve_sh(r, c, sh_a, sh_b, 1e-9).double()  # [V, 4, 3]
    b = sh_basis(d.reshape(-1, 3), 1).reshape(50, 30, 4).double()
    residual = colours - 0.5 - torch.einsum("vmk,vkc->vmc", b, sh)
    normal = torch.einsum("vm,vmk,vmc->vkc", w, b, residual)
    assert normal.abs().max() < 1e-5


def test_an_unobserved_direction_with_no_ridge_gives_a_finite_fit_that_reproduces_what_was_seen():
    # every observation from one direction: the degree-1 terms are undetermined without the ridge;
    # the fast path must neither blow up nor lose the colour seen from that direction
    (r, c, sh_a, sh_b), (d, w, colours) = streamed_sums(1, voxels=20, observations=12, seed=5, directions=1,
                                                        dtype=torch.float64)
    sh = solve_sh(r, c, sh_a, sh_b, 0.0).double()
    assert torch.isfinite(sh).all() and sh.abs().max() < 10.0
    b = sh_basis(d[:, 0], 1).double()  # [V, 4], the one direction
    seen = 0.5 + torch.einsum("vk,vkc->vc", b, sh)
    mean = (w[:, :, None] * colours).sum(1) / w.sum(1, keepdim=True)
    assert torch.allclose(seen, mean, atol=1e-6)


@pytest.mark.realdata
@pytest.mark.parametrize("capture", ["realsense_shelf", "apc_bins/bin_labels"])
def test_the_decoders_fields_are_the_scene_fields_bit_for_bit(capture, shelf_dir, apc_bins_path):
    # read as a decode reads them: strided views of the scene's records, labels where they were fused
    frames = load_dataset(shelf_dir if capture == "realsense_shelf" else apc_bins_path / "bin_labels", max_frames=4)
    scene = Scene(SceneConfig(voxel_size=0.008))
    for frame in frames:
        scene.fold(frame)
    sums = scene.decode_inputs().sums
    fields, decoded = fields_from_sums(sums, scene.config, sort=False), decoder_fields(sums, scene.config)
    assert set(decoded) == {"features", "sh"} | ({"labels"} if capture != "realsense_shelf" else set())
    assert len(decoded["features"]) > 10_000
    for name, value in decoded.items():
        assert value.dtype == fields[name].dtype and torch.equal(value, fields[name]), name


@pytest.mark.realdata
@pytest.mark.parametrize("degree", [0, 2])
def test_the_decoders_sh_fit_is_the_scene_fields_at_every_sh_degree(degree, shelf_frames):
    scene = Scene(SceneConfig(voxel_size=0.01, sh_degree=degree))
    for frame in shelf_frames[:3]:
        scene.fold(frame)
    sums = scene.decode_inputs().sums
    fit = decoder_fields(sums, scene.config)["sh"]
    assert fit.shape == (len(scene), (degree + 1) ** 2, 3)
    assert torch.equal(fit, fields_from_sums(sums, scene.config, sort=False)["sh"])


@pytest.mark.realdata
def test_fast_solve_matches_the_reference_on_the_real_capture(shelf_frames):
    scene = Scene(SceneConfig(voxel_size=0.008))
    for frame in shelf_frames[:3]:
        scene.fold(frame)
    s = sums_from_stored({k: torch.as_tensor(v) for k, v in scene.sums().items()})
    args = (s["r_sum"] + 1e-8, s["rgb_sum"], s["sh_a"], s["sh_b"], scene.config.decoder.sh_regularization)
    fast, ref = solve_sh(*args), solve_sh_reference(*args)
    assert len(fast) > 10_000
    assert torch.allclose(fast, ref, rtol=1e-4, atol=1e-5)


def test_a_gradient_reaches_the_sums_through_the_reference():
    (r, c, sh_a, sh_b), _ = streamed_sums(1, voxels=10, observations=8)
    c = c.clone().requires_grad_(True)
    sh = solve_sh(r, c, sh_a, sh_b, 0.003)
    sh[:, 0].sum().backward()
    assert c.grad is not None and c.grad.abs().sum() > 0
    assert torch.allclose(sh.detach(), solve_sh(r, c.detach(), sh_a, sh_b, 0.003), rtol=1e-4, atol=1e-5)


def test_empty_and_mismatched_sums():
    (r, c, sh_a, sh_b), _ = streamed_sums(1, voxels=4, observations=5)
    assert solve_sh(r[:0], c[:0], sh_a[:0], sh_b[:0], 0.003).shape == (0, 4, 3)
    with pytest.raises(ValueError, match=re.escape("sh_a: expected [4, 9] for K = 4, got [4, 8]")):
        solve_sh(r, c, sh_a[:, :8], sh_b, 0.003)
    with pytest.raises(ValueError, match=re.escape("color_sum [3, 3]")):
        solve_sh(r, c[:3], sh_a, sh_b, 0.003)
    with pytest.raises(ValueError, match="sh_b"):
        solve_sh_reference(r, c, sh_a, sh_b[:, :7], 0.003)
