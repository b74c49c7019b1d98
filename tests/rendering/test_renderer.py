"""render(): the fast path against the reference, closed-form cases, edge cases, gradients."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numba
import pytest
import torch

from canonical_core.gaussians import Gaussians
from canonical_core.rendering import render

from .scenes import gaussians_at, look_at_camera, pinhole, random_scene

ALL_OUTPUTS = ("rgb", "depth", "alpha", "features", "labels")
LOW_PASS = 0.3  # px^2, the image model's floor on the 2D covariance
RED, GREEN, BLUE = (0.9, 0.1, 0.1), (0.1, 0.9, 0.1), (0.1, 0.1, 0.9)

# (seed, n, sh degree, scale range, opacity range, camera distance): sparse scenes, dense ones
# where pixels terminate early, and a camera inside the cloud so Gaussians straddle the near plane.
SCENES = [
    (0, 150, 0, (0.02, 0.15), (0.05, 1.0), 3.0),
    (1, 300, 1, (0.02, 0.15), (0.05, 1.0), 3.0),
    (2, 300, 2, (0.05, 0.3), (0.6, 1.0), 2.5),
    (3, 400, 3, (0.02, 0.2), (0.3, 1.0), 0.6),
    (4, 800, 3, (0.05, 0.25), (0.8, 1.0), 2.0),
    (5, 500, 1, (0.01, 0.5), (0.05, 1.0), 1.5),
]


@pytest.mark.parametrize("seed,n,sh_degree,scales,opacities,distance", SCENES)
def test_cpu_matches_reference(seed, n, sh_degree, scales, opacities, distance):
    gaussians = random_scene(n, seed, sh_degree=sh_degree, scale_range=scales, opacity_range=opacities)
    angle = seed * 1.3
    eye = [distance * math.sin(angle), 0.4 * distance * math.cos(seed), -distance * math.cos(angle)]
    # 45 x 37 is not a multiple of the 16 px tile: the last tiles overhang the image.
    camera = look_at_camera(45, 37, 40.0, eye, [0.1, -0.1, 0.0], roll=0.4 * seed)
    reference = render(gaussians, camera, ALL_OUTPUTS, background=(0.2, 0.4, 0.6), backend="reference")
    fast = render(gaussians, camera, ALL_OUTPUTS, background=(0.2, 0.4, 0.6), backend="cpu")
    assert (reference.alpha > 0).float().mean() > 0.3, "the scene should cover much of the image"
    # RGB alone takes the C compositor's planar (channel-major) path; with features and labels
    # (12 channels) it takes the pixel-major one.
    rgb_only = render(gaussians, camera, ("rgb", "depth", "alpha"), background=(0.2, 0.4, 0.6), backend="cpu")
    for result, names in ((fast, ("rgb", "depth", "alpha", "features")), (rgb_only, ("rgb", "depth", "alpha"))):
        for name in names:
            difference = (getattr(reference, name) - getattr(result, name)).abs().max().item()
            assert difference <= 1e-4, f"{name}: max |reference - cpu| = {difference:.3g}"
    # Labels are an argmax: compare where the top two composited label scores are clearly apart.
    scores = render(replace(gaussians, features=gaussians.labels), camera, ("features",), backend="reference").features
    top2 = scores.topk(2, dim=-1).values
    decided = (top2[..., 0] - top2[..., 1] > 1e-4) | (reference.labels == -1)
    assert fast.labels.dtype == torch.int64
    assert torch.equal(reference.labels[decided], fast.labels[decided])


def test_dense_scene_terminates_early_in_both_backends():
    gaussians = random_scene(800, 4, scale_range=(0.05, 0.25), opacity_range=(0.8, 1.0))
    camera = look_at_camera(32, 32, 30.0, [0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    for backend in ("reference", "cpu"):
        alpha = render(gaussians, camera, ("alpha",), backend=backend).alpha
        # Early termination leaves T in [1e-4, 1e-2]: alpha stops short of 1 - 1e-4.
        assert alpha.max() > 0.999 and alpha.max() <= 1 - 1e-4 + 1e-6


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_isotropic_gaussian_head_on_has_closed_form_alpha(backend):
    z, scale, opacity, focal = 2.0, 0.01, 0.8, 100.0
    camera = pinhole(32, 24, focal, cx=15.3, cy=11.6)  # the mean projects between pixel centres
    result = render(gaussians_at([0, 0, z], [scale] * 3, [opacity], [GREEN]), camera, backend=backend)
    # On the optical axis J = diag(f / z): Sigma_2D = ((f s / z)^2 + 0.3) I.
    variance = (focal * scale / z) ** 2 + LOW_PASS
    v, u = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    q = ((u - 15.3) ** 2 + (v - 11.6) ** 2) / variance
    alpha = torch.clamp(opacity * torch.exp(-0.5 * q), max=0.99)
    alpha = torch.where((q <= 9) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
    assert (result.alpha - alpha).abs().max() < 1e-5
    assert torch.allclose(result.depth[alpha > 0], torch.tensor(z)) and (result.depth[alpha == 0] == 0).all()
    assert torch.allclose(result.rgb, alpha[..., None] * torch.tensor(GREEN), atol=1e-5)
    assert result.features is None and result.labels is None


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_pixel_centres_are_integer_coordinates(backend):
    camera = pinhole(20, 16, 50.0, cx=9.5, cy=7.5)
    # A small Gaussian whose mean projects exactly onto pixel (u, v) = (12, 5).
    z = 3.0
    mean = [(12 - 9.5) * z / 50.0, (5 - 7.5) * z / 50.0, z]
    alpha = render(gaussians_at(mean, [0.005] * 3, [0.9], [RED]), camera, ("alpha",), backend=backend).alpha
    assert divmod(int(alpha.argmax()), 20) == (5, 12)
    assert abs(alpha[5, 11] - alpha[5, 13]) < 1e-5 and abs(alpha[4, 12] - alpha[6, 12]) < 1e-5


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_opaque_gaussians_composite_in_depth_order_regardless_of_input_order(backend):
    camera = pinhole(16, 16, 40.0, cx=7.0, cy=7.0)  # both means project onto pixel (7, 7)
    means, scales = [[0, 0, 2.0], [0, 0, 3.0]], [[0.2] * 3, [0.3] * 3]
    front_first = render(gaussians_at(means, scales, [0.99, 0.95], [RED, BLUE]), camera, backend=backend)
    back_first = render(gaussians_at(means[::-1], scales[::-1], [0.95, 0.99], [BLUE, RED]), camera, backend=backend)
    for name in ("rgb", "depth", "alpha"):
        assert torch.allclose(getattr(front_first, name), getattr(back_first, name), atol=1e-6), name
    # At pixel (7, 7) the red one has alpha 0.99 and leaves T = 0.01 for the blue one (0.95).
    expected = 0.99 * torch.tensor(RED) + 0.01 * 0.95 * torch.tensor(BLUE)
    assert torch.allclose(front_first.rgb[7, 7], expected, atol=1e-5)
    assert front_first.depth[7, 7] == pytest.approx((0.99 * 2 + 0.0095 * 3) / (0.99 + 0.0095), abs=1e-5)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_median_depth_is_the_surface_that_covers_most_of_the_pixel(backend):
    camera = pinhole(16, 16, 40.0, cx=7.0, cy=7.0)  # every mean projects onto pixel (7, 7)
    scales = [[0.2] * 3] * 3
    # alpha 0.3 at 2 m (T 0.7), 0.6 at 3 m (T 0.28: below 1/2 here), 0.9 at 4 m
    layers = gaussians_at([[0, 0, 2.0], [0, 0, 3.0], [0, 0, 4.0]], scales, [0.3, 0.6, 0.9], [RED, GREEN, BLUE])
    median = render(layers, camera, ("depth", "alpha"), depth_mode="median", backend=backend)
    expected = render(layers, camera, ("depth", "alpha"), depth_mode="expected", backend=backend)
    assert median.depth[7, 7] == pytest.approx(3.0, abs=1e-6)
    weights = torch.tensor([0.3, 0.7 * 0.6, 0.28 * 0.9])
    assert expected.depth[7, 7] == pytest.approx(float((weights * torch.tensor([2.0, 3.0, 4.0])).sum() / weights.sum()), abs=1e-5)
    assert torch.equal(median.alpha, expected.alpha)
    # where a pixel stays more than half transparent, the median depth is the expected one
    thin = median.alpha < 0.5
    assert thin.any() and torch.equal(median.depth[thin], expected.depth[thin])
    assert (median.depth[median.alpha == 0] == 0).all()


@pytest.mark.parametrize("seed,n,sh_degree,scales,opacities,distance", SCENES[:4])
def test_median_depth_of_the_cpu_backend_matches_the_reference(seed, n, sh_degree, scales, opacities, distance):
    gaussians = random_scene(n, seed, sh_degree=sh_degree, scale_range=scales, opacity_range=opacities)
    camera = look_at_camera(45, 37, 40.0, [0.3 * seed, 0.2, -distance], [0.1, -0.1, 0.0], roll=0.4 * seed)
    reference = render(gaussians, camera, ("depth", "alpha"), depth_mode="median", backend="reference")
    fast = render(gaussians, camera, ("depth", "alpha"), depth_mode="median", backend="cpu")
    expected = render(gaussians, camera, ("depth",), backend="cpu")
    crossed = reference.alpha >= 0.5
    assert crossed.float().mean() > 0.2
    # a pixel whose transmittance lands within rounding of 1/2 may pick the neighbouring splat
    same = (reference.depth - fast.depth).abs() <= 1e-5
    assert same.float().mean() > 0.999, f"{int((~same).sum())} pixels differ"
    assert not torch.equal(fast.depth[crossed], expected.depth[crossed])  # it is not the expected depth


def test_an_unknown_depth_mode_is_refused():
    camera = pinhole(8, 8, 20.0, cx=3.5, cy=3.5)
    with pytest.raises(ValueError, match="^depth_mode: expected one of"):
        render(gaussians_at([0, 0, 2.0], [0.1] * 3, [0.5], [RED]), camera, depth_mode="mean")


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_stops_before_the_splat_that_would_drop_transmittance_below_1e_4(backend):
    # Six stacked layers of alpha 0.8 at the centre: T = 0.2^k. The sixth would leave
    # T = 6.4e-5 < 1e-4, so 3DGS stops before it: five layers count, T_final = 0.2^5.
    camera = pinhole(8, 8, 40.0, cx=3.0, cy=3.0)  # the means project onto pixel (3, 3)
    colors = [(0.1 * k, 0.5, 1 - 0.1 * k) for k in range(6)]
    means = [[0, 0, 2.0 + 0.1 * k] for k in range(6)]
    result = render(gaussians_at(means, [[0.3] * 3] * 6, [0.8] * 6, colors), camera, backend=backend)
    weights = torch.tensor([0.8 * 0.2**k for k in range(5)])
    assert result.alpha[3, 3] == pytest.approx(1 - 0.2**5, abs=1e-6)
    expected_rgb = (weights[:, None] * torch.tensor(colors[:5])).sum(0)
    assert torch.allclose(result.rgb[3, 3], expected_rgb, atol=1e-5)


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_background_fills_what_the_gaussians_leave(backend):
    camera = pinhole(12, 12, 30.0, cx=5.5, cy=5.5)
    result = render(gaussians_at([0, 0, 2.0], [0.05] * 3, [0.5], [RED]), camera, background=(0.0, 1.0, 0.0), backend=backend)
    transmittance = 1 - result.alpha
    expected = (1 - transmittance)[..., None] * torch.tensor(RED) + transmittance[..., None] * torch.tensor([0.0, 1.0, 0.0])
    assert torch.allclose(result.rgb, expected, atol=1e-5)
    assert result.rgb[0, 0].tolist() == [0.0, 1.0, 0.0]


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_normalised_colour_is_the_blend_over_its_weight(backend):
    # a half-transparent red splat in front of the green background: composited, its pixels darken
    # toward the background with their alpha; normalised, every pixel it touches is red, and the
    # background shows only where nothing is drawn
    camera = pinhole(12, 12, 30.0, cx=5.5, cy=5.5)
    splat = gaussians_at([0, 0, 2.0], [0.05] * 3, [0.5], [RED])
    composited = render(splat, camera, background=(0.0, 1.0, 0.0), backend=backend)
    normalised = render(splat, camera, background=(0.0, 1.0, 0.0), colour="normalised", backend=backend)
    drawn = composited.alpha > 0
    assert 0 < drawn.float().mean() < 1 and composited.alpha.max() < 0.6
    assert torch.allclose(normalised.rgb[drawn], torch.tensor(RED).expand(int(drawn.sum()), 3), atol=1e-5)
    assert (normalised.rgb[~drawn] == torch.tensor([0.0, 1.0, 0.0])).all()
    for name in ("alpha", "depth"):  # only the colour changes
        assert torch.equal(getattr(normalised, name), getattr(composited, name))
    # two overlapping splats: the normalised colour is their weighted mean, whatever their opacity
    pair = gaussians_at([[0, 0, 2.0], [0.02, 0, 2.5]], [[0.05] * 3] * 2, [0.3, 0.6], [RED, BLUE])
    out = render(pair, camera, ("rgb", "alpha"), colour="normalised", backend=backend)
    black = render(pair, camera, ("rgb", "alpha"), backend=backend)  # over black: the bare blend sum(w c)
    seen = out.alpha > 1e-3
    assert torch.allclose(out.rgb[seen], (black.rgb / black.alpha[..., None])[seen], atol=1e-4)


@pytest.mark.parametrize("seed,n,sh_degree,scales,opacities,distance", SCENES[:3])
def test_normalised_colour_cpu_matches_reference(seed, n, sh_degree, scales, opacities, distance):
    gaussians = random_scene(n, seed, sh_degree=sh_degree, scale_range=scales, opacity_range=opacities)
    camera = look_at_camera(45, 37, 40.0, [0.0, 0.4 * distance, -distance], [0.1, -0.1, 0.0], roll=0.4 * seed)
    reference = render(gaussians, camera, ("rgb", "alpha"), colour="normalised", backend="reference")
    fast = render(gaussians, camera, ("rgb", "alpha"), colour="normalised", backend="cpu")
    # where a pixel is barely touched the division magnifies float32 round-off: compare where drawn
    drawn = reference.alpha > 1e-2
    assert drawn.float().mean() > 0.3
    assert (reference.rgb[drawn] - fast.rgb[drawn]).abs().max() <= 1e-3


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_empty_scene_returns_the_background(backend):
    camera = pinhole(10, 7, 20.0, cx=5.0, cy=3.0)
    empty = Gaussians.empty(sh_degree=2, feature_dim=3, label_dim=2)
    result = render(empty, camera, ALL_OUTPUTS, background=[0.1, 0.2, 0.3], backend=backend)
    assert torch.allclose(result.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(7, 10, 3))
    assert (result.alpha == 0).all() and (result.depth == 0).all() and (result.features == 0).all()
    assert result.features.shape == (7, 10, 3) and (result.labels == -1).all()


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_gaussians_behind_or_on_the_camera_plane_contribute_nothing(backend):
    camera = pinhole(16, 16, 20.0, cx=7.5, cy=7.5)
    behind = gaussians_at([[0, 0, -1.0], [0.1, 0, -0.2], [0, 0, 0.0], [0, 0, 0.005]], [[0.5] * 3] * 4, [1.0] * 4, [RED] * 4)
    result = render(behind, camera, backend=backend)
    assert (result.alpha == 0).all() and (result.rgb == 0).all()


@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_degenerate_and_huge_gaussians_render_finite_images_quickly(backend):
    camera = look_at_camera(40, 30, 35.0, [0.0, 0.0, -2.0], [0.0, 0.0, 0.0])
    means = [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.2, 0.2, 0], [0, 0, -1.9], [0, 0, -2.0 + 1e-9], [0.3, 0, 0], [0, 0, 0]]
    scales = [
        [0.0, 0.0, 0.0],  # a point: only the low-pass is left
        [0.3, 0.0, 0.0],  # a line: singular 3D covariance
        [0.2, 0.2, 0.0],  # a flat disc: singular along z
        [1e20, 1e20, 1e20],  # overflows float32 once squared
        [5.0, 5.0, 5.0],  # fills the image from just in front of the camera
        [0.1, 0.1, 0.1],  # on the camera plane
        [1e3, 1e-6, 1e3],  # an enormous sheet
        [0.1, 0.1, 0.1],  # gets a zero quaternion below
    ]
    gaussians = gaussians_at(means, scales, [0.9] * 8, [RED, GREEN, BLUE, RED, GREEN, BLUE, RED, GREEN])
    gaussians.quats[7] = 0.0  # zero quaternion
    start = time.perf_counter()
    result = render(gaussians, camera, backend=backend)
    assert time.perf_counter() - start < 5.0
    for name in ("rgb", "depth", "alpha"):
        assert torch.isfinite(getattr(result, name)).all(), name
    assert result.alpha.max() > 0.5 and result.rgb.min() >= 0 and result.rgb.max() <= 1


def test_many_screen_filling_gaussians_are_bounded_by_the_image():
    camera = pinhole(64, 48, 50.0, cx=31.5, cy=23.5)
    n = 2000
    means = torch.rand(n, 3) + torch.tensor([0, 0, 0.5])
    gaussians = gaussians_at(means, torch.full((n, 3), 50.0), torch.full((n,), 0.5), torch.rand(n, 3))
    start = time.perf_counter()
    result = render(gaussians, camera, backend="cpu")
    assert time.perf_counter() - start < 5.0 and torch.isfinite(result.rgb).all()


def test_thread_count_does_not_change_the_image_and_is_restored():
    gaussians = random_scene(300, 7)
    camera = look_at_camera(40, 40, 35.0, [0.0, 0.5, -3.0], [0.0, 0.0, 0.0])
    before = numba.get_num_threads()
    one = render(gaussians, camera, ALL_OUTPUTS, backend="cpu", num_threads=1)
    many = render(gaussians, camera, ALL_OUTPUTS, backend="cpu", num_threads=64)  # clamped to the cores
    assert numba.get_num_threads() == before
    for name in ALL_OUTPUTS:
        assert torch.equal(getattr(one, name), getattr(many, name)), name


def test_auto_backend_on_cpu_is_the_fast_path():
    gaussians = random_scene(100, 8)
    camera = look_at_camera(24, 24, 25.0, [0.0, 0.0, -3.0], [0.0, 0.0, 0.0])
    auto = render(gaussians, camera, ALL_OUTPUTS)
    fast = render(gaussians, camera, ALL_OUTPUTS, backend="cpu")
    assert all(torch.equal(getattr(auto, name), getattr(fast, name)) for name in ALL_OUTPUTS)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(outputs=("rgb", "features")), "features"),
        (dict(outputs=("labels",)), "labels"),
        (dict(outputs=("rgb", "normals")), "outputs"),
        (dict(outputs="rgb"), "outputs"),
        (dict(outputs=()), "outputs"),
        (dict(background=[0.0, 1.0]), r"background.*\[2\]"),
        (dict(background=[float("nan"), 0.0, 0.0]), r"^background: expected finite values, got \[nan, 0.0, 0.0\]"),
        (dict(background=(0.0, float("inf"), 0.0)), r"^background: expected finite values, got \[0.0, inf, 0.0\]"),
        (dict(background="white"), r"^background: expected an rgb colour of 3 numbers, got 'white'"),
        (dict(backend="opengl"), "backend"),
        (dict(colour="premultiplied"), "colour"),
        (dict(backend="gsplat"), "backend"),
        (dict(near_plane=0.0), "near_plane"),
        (dict(near_plane=float("inf")), "^near_plane: expected a positive, finite distance"),  # it culled everything
        (dict(num_threads=0), "num_threads"),
    ],
)
def test_bad_arguments_raise_value_errors_naming_the_field(kwargs, field):
    gaussians = gaussians_at([0, 0, 2.0], [0.1] * 3, [0.5], [RED])  # no features, no labels
    with pytest.raises(ValueError, match=field):
        render(gaussians, pinhole(8, 8, 10.0, 3.5, 3.5), **kwargs)


def test_reference_gradients_match_finite_differences():
    torch.manual_seed(0)
    dtype = torch.float64
    camera = pinhole(12, 10, 14.0, cx=5.7, cy=4.4)
    means = torch.tensor([[0.05, 0.02, 1.0], [-0.1, 0.05, 1.2], [0.06, -0.08, 1.4]], dtype=dtype)
    scales = torch.tensor([[0.08, 0.05, 0.06], [0.1, 0.07, 0.05], [0.06, 0.09, 0.12]], dtype=dtype)
    quats = torch.tensor([[0.9, 0.1, -0.2, 0.3], [0.7, -0.3, 0.2, 0.1], [0.5, 0.5, 0.1, -0.4]], dtype=dtype)
    opacities = torch.tensor([0.7, 0.5, 0.6], dtype=dtype)
    sh = torch.randn(3, 4, 3, dtype=dtype) * 0.1  # degree 1, colours stay inside (0, 1)
    features = torch.randn(3, 2, dtype=dtype)

    def rendered(means, scales, quats, opacities, sh, features):
        gaussians = Gaussians(means=means, scales=scales, quats=quats, opacities=opacities, sh=sh, features=features)
        outputs = ("rgb", "depth", "alpha", "features")
        result = render(gaussians, camera, outputs, background=(0.3, 0.2, 0.1), backend="reference")
        return torch.cat([getattr(result, name).flatten() for name in outputs])

    inputs = tuple(t.requires_grad_() for t in (means, scales, quats, opacities, sh, features))
    assert torch.autograd.gradcheck(rendered, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)
