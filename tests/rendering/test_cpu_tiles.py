"""Pieces of the cpu backend: the C compositor's depth sort held to numpy, and every build of the
compositor held to the one that render() uses (which test_renderer holds to the reference)."""

import numba
import numpy as np
import pytest
import torch

from canonical_core.rendering import cpu_tiles
from canonical_core.rendering.cpu_tiles import compositor_build, compositor_builds, load_compositor, stable_depth_order

from .scenes import look_at_camera, random_scene


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000, 20000])
def test_stable_depth_order_equals_numpy_stable_argsort(n):
    # few distinct depths (many ties: input order must be kept) spread over several float exponents
    rng = np.random.default_rng(n)
    depths = rng.choice(rng.uniform(0.01, 300.0, max(n // 4, 1)), n).astype(np.float32)
    assert np.array_equal(stable_depth_order(depths), np.argsort(depths, kind="stable"))


def test_stable_depth_order_of_equal_depths_is_the_identity():
    assert np.array_equal(stable_depth_order(np.full(300, 2.5, np.float32)), np.arange(300))


def test_stable_depth_order_rejects_float64_depths():
    with pytest.raises(ValueError, match="depths: expected a C-contiguous float32 array"):
        stable_depth_order(np.ones(4))


def test_the_baseline_build_is_always_there_and_the_loaded_one_is_a_build():
    assert "_composite" in compositor_builds() and compositor_build in compositor_builds()


@pytest.mark.parametrize("build_name", sorted(compositor_builds()))
def test_every_build_gives_the_image_of_the_loaded_build(build_name):
    if build_name.endswith("x86_64_v3") and not load_compositor("_composite").canonical_cpu_has_x86_64_v3():
        pytest.skip("this CPU cannot run the x86-64-v3 build")
    # dense and sparse parts, 61 x 47: tiles overhang the image on two sides
    gaussians = random_scene(1500, 11, sh_degree=1, scale_range=(0.01, 0.3), opacity_range=(0.05, 1.0))
    camera = look_at_camera(61, 47, 45.0, [0.3, -0.5, -2.5], [0.0, 0.0, 0.0], roll=0.2)
    threads = min(2, numba.config.NUMBA_NUM_THREADS)
    loaded = cpu_tiles.render_cpu(gaussians, camera, ("rgb", "features"), 0.01, threads, median_depth=True)
    built = cpu_tiles.render_cpu(gaussians, camera, ("rgb", "features"), 0.01, threads, load_compositor(build_name),
                                 median_depth=True)
    assert (loaded.transmittance < 0.5).float().mean() > 0.3, "the scene should cover much of the image"
    for name, a, b in zip(loaded._fields, loaded, built):
        assert torch.allclose(a, b, rtol=0, atol=2e-6), f"{name}: max diff {(a - b).abs().max().item():.3g}"
    # without the median depth the sums are the same, and no median map comes back
    plain = cpu_tiles.render_cpu(gaussians, camera, ("rgb", "features"), 0.01, threads, load_compositor(build_name))
    assert plain.median_depth is None and all(torch.equal(a, b) for a, b in zip(plain[:4], built[:4]))
