"""blend_weights: the fast path against the reference, and the weights against the render."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core.rendering import render
from canonical_core.rendering.projection import channel_values
from canonical_core.rendering.renderer import blend_rgb
from canonical_core.rendering.weights import blend_weight_rows, blend_weights, weight_rows_and_blend

from .scenes import gaussians_at, look_at_camera, pinhole, random_scene


def dense(w, camera, n: int) -> torch.Tensor:  # [H * W, N]
    return torch.zeros(camera.height * camera.width, n, dtype=torch.float64).index_put_(
        (w.pixels, w.ids), w.weights.double(), accumulate=True)


@pytest.fixture(scope="module")
def scene():
    g = random_scene(300, seed=3, feature_dim=None, label_dim=None, opacity_range=(0.1, 0.95))
    camera = look_at_camera(45, 37, 40.0, eye=[0.3, -0.2, -3.0], target=[0, 0, 0])
    return g, camera


def test_fast_path_equals_the_reference(scene):
    g, camera = scene
    fast, reference = blend_weights(g, camera, backend="cpu"), blend_weights(g, camera, backend="reference")
    assert len(fast.weights) > 1000
    difference = (dense(fast, camera, len(g)) - dense(reference, camera, len(g))).abs().max()
    assert difference < 1e-6


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_weights_reproduce_the_render(scene, backend):
    g, camera = scene
    w = blend_weights(g, camera, backend=backend, min_weight=0.0)
    colours = channel_values(g, camera, ("rgb",))
    image = torch.zeros(camera.height * camera.width, 3).index_add_(0, w.pixels, w.weights[:, None] * colours[w.ids])
    rgb = render(g, camera, outputs=("rgb",)).rgb.reshape(-1, 3)
    assert (image.clamp(0, 1) - rgb).abs().max() < 1e-5


def test_no_entry_weighs_zero_on_either_backend(scene):
    """At ``min_weight`` 0 an entry is still a weight the pixel takes: both backends list the same
    entries, none of them zero (the reference once listed every pixel of every tile it visited)."""
    g, camera = scene
    fast, reference = (blend_weights(g, camera, backend=b, min_weight=0.0) for b in ("cpu", "reference"))
    assert bool((fast.weights > 0).all()) and bool((reference.weights > 0).all())
    assert len(fast.weights) == len(reference.weights)


def test_min_weight_drops_only_the_small_weights(scene):
    g, camera = scene
    every, some = blend_weights(g, camera, min_weight=0.0), blend_weights(g, camera, min_weight=0.05)
    assert bool((some.weights >= 0.05).all())
    assert len(some.weights) == int((every.weights >= 0.05).sum()) < len(every.weights)


def test_the_front_gaussian_takes_its_opacity_and_the_one_behind_the_rest():
    g = gaussians_at([[0, 0, 2], [0, 0, 3]], [[1.0, 1.0, 0.01]] * 2, [0.6, 0.5], [[1, 0, 0], [0, 1, 0]])
    camera = pinhole(8, 8, 10.0, 3.0, 3.0)  # both centres fall on pixel (3, 3): q = 0 there
    w = blend_weights(g, camera)
    at_centre = {int(i): float(v) for p, i, v in zip(w.pixels, w.ids, w.weights) if p == 3 * 8 + 3}
    assert at_centre == pytest.approx({0: 0.6, 1: 0.5 * (1 - 0.6)}, rel=1e-6)


def test_a_scene_behind_the_camera_has_no_weights():
    g = gaussians_at([[0, 0, -2]], [[0.1] * 3], [0.9], [[1, 1, 1]])
    for backend in ("cpu", "reference"):
        w = blend_weights(g, pinhole(16, 16, 10.0, 7.5, 7.5), backend=backend)
        assert len(w.pixels) == len(w.ids) == len(w.weights) == 0


def test_bad_arguments_name_the_field(scene):
    g, camera = scene
    with pytest.raises(ValueError, match="backend"):
        blend_weights(g, camera, backend="gpu")
    with pytest.raises(ValueError, match="min_weight"):
        blend_weights(g, camera, min_weight=-1.0)
    for near in (-1.0, 0.0, float("nan"), float("inf")):  # as `render` refuses it: behind the camera would count
        for weights in (blend_weights, blend_weight_rows, weight_rows_and_blend):
            with pytest.raises(ValueError, match="^near_plane: "):
                weights(g, camera, near_plane=near)


def row_entries(rows, num_pixels: int) -> torch.Tensor:  # [P, 2]: (pixel, id) of each entry, in row order
    pixels = torch.repeat_interleave(torch.arange(num_pixels), torch.from_numpy(np.diff(rows.starts.astype(np.int64))))
    return torch.stack([pixels, torch.from_numpy(rows.ids).long()], 1)


@pytest.mark.parametrize("normalised_from", [None, 0.5])
def test_rows_hold_the_weights_of_each_pixel_front_to_back(scene, normalised_from):
    g, camera = scene
    num_pixels = camera.height * camera.width
    w = blend_weights(g, camera)
    rows = blend_weight_rows(g, camera, normalised_from)
    assert rows.starts.dtype == np.int32 and rows.ids.dtype == np.int32 and rows.scale.shape == (num_pixels,)
    alpha = torch.zeros(num_pixels, dtype=torch.float64).index_add_(0, w.pixels, w.weights.double())
    kept = torch.ones(num_pixels, dtype=torch.bool) if normalised_from is None else alpha >= normalised_from
    assert 0.05 < kept.float().mean() <= 1.0
    expected = dense(w, camera, len(g)) * torch.where(kept, 1 / alpha.clamp_min(1e-12) if normalised_from else 1.0, 0.0)[:, None]
    got = torch.zeros_like(expected).index_put_(tuple(row_entries(rows, num_pixels).T), torch.from_numpy(rows.weights).double())
    assert (got - expected).abs().max() < 1e-6
    assert np.allclose(rows.scale, np.where(kept, 1 / alpha.clamp_min(1e-12), 0.0) if normalised_from else 1.0)
    # within a row the entries keep the compositing order: the same Gaussians as blend_weights lists them
    for p in torch.nonzero(kept).flatten()[:50].tolist():
        assert rows.ids[rows.starts[p]:rows.starts[p + 1]].tolist() == w.ids[w.pixels == p].tolist()


@pytest.mark.parametrize("normalised_from", [None, 0.5])
def test_fast_rows_equal_the_reference_rows(scene, normalised_from):
    g, camera = scene
    fast = blend_weight_rows(g, camera, normalised_from, backend="cpu")
    reference = blend_weight_rows(g, camera, normalised_from, backend="reference")
    num_pixels = camera.height * camera.width
    assert len(fast.ids) > 1000

    def matrix(rows):
        return torch.zeros(num_pixels, len(g), dtype=torch.float64).index_put_(
            tuple(row_entries(rows, num_pixels).T), torch.from_numpy(rows.weights).double(), accumulate=True)

    assert (matrix(fast) - matrix(reference)).abs().max() < 1e-5
    assert np.allclose(fast.scale, reference.scale, rtol=1e-5)


def test_rows_of_a_scene_behind_the_camera_are_empty():
    g = gaussians_at([[0, 0, -2]], [[0.1] * 3], [0.9], [[1, 1, 1]])
    camera = pinhole(16, 16, 10.0, 7.5, 7.5)
    for backend in ("cpu", "reference"):
        for rows in (blend_weight_rows(g, camera, 0.5, backend=backend), weight_rows_and_blend(g, camera, 0.5, backend)[0]):
            assert len(rows.ids) == 0 and not rows.starts.any() and not rows.scale.any()
        blend = weight_rows_and_blend(g, camera, 0.5, backend)[1]
        assert not blend.values.any() and not blend.weight_sums.any() and (blend.transmittance == 1).all()


@pytest.mark.parametrize("normalised_from", [None, 0.5])
@pytest.mark.parametrize("min_weight", [1e-4, 0.02])
def test_rows_and_blend_are_the_rows_and_the_render_from_one_pass(scene, normalised_from, min_weight):
    g, camera = scene
    rows, blend = weight_rows_and_blend(g, camera, normalised_from, min_weight=min_weight)
    for got, expected in zip(rows, blend_weight_rows(g, camera, normalised_from, min_weight=min_weight)):
        assert np.array_equal(got, expected)
    # the blend keeps every weight, whatever the rows leave out: the render's own image, bit for bit
    assert blend.depth_sums is None
    for colour in ("composited", "normalised"):
        out = render(g, camera, outputs=("rgb", "alpha"), colour=colour, backend="cpu")
        assert torch.equal(blend_rgb(blend, colour), out.rgb)
        assert torch.equal(1 - blend.transmittance, out.alpha)
    if min_weight > 1e-4:  # the rows did leave weights out
        assert len(rows.weights) < len(blend_weight_rows(g, camera, normalised_from).weights)


def test_the_reference_rows_and_blend_agree_with_the_fast_ones(scene):
    g, camera = scene
    (fast_rows, fast), (reference_rows, reference) = (weight_rows_and_blend(g, camera, 0.5, backend) for backend in ("cpu", "reference"))
    assert np.allclose(fast_rows.scale, reference_rows.scale, rtol=1e-5)
    for colour in ("composited", "normalised"):
        assert (blend_rgb(fast, colour) - blend_rgb(reference, colour)).abs().max() < 1e-4
    assert (fast.transmittance - reference.transmittance).abs().max() < 1e-5


def test_rows_name_a_bad_normalisation(scene):
    g, camera = scene
    for bad in (0.0, -1.0, True, "0.5"):
        with pytest.raises(ValueError, match="^normalised_from: expected a positive alpha or None"):
            blend_weight_rows(g, camera, bad)
    with pytest.raises(ValueError, match="backend"):
        blend_weight_rows(g, camera, backend="gpu")
    for bad in (0.0, "0.5"):
        with pytest.raises(ValueError, match="^normalised_from: expected a positive alpha or None"):
            weight_rows_and_blend(g, camera, bad)
    with pytest.raises(ValueError, match="min_weight"):
        weight_rows_and_blend(g, camera, min_weight=-1.0)
