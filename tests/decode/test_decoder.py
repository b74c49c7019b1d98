import math

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.calibration import quaternion_to_matrix
from canonical_core.decode import (FOOTPRINT_GAIN, FULL_VOXEL_EXTENT, GaussianDecoder, MonotoneOpacity, matrix_to_quaternion,
                                   support_unit)
from canonical_core.decode.decoder import OPACITY_BIAS, OPACITY_SLOPE
from canonical_core.gaussians.container import SH_C0
from canonical_core.scene import Scene


@pytest.mark.parametrize("seed", range(5))
def test_opacity_is_non_decreasing_in_support_for_any_weights(seed):
    head = MonotoneOpacity()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in head.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 5)  # negative values included
    support = torch.linspace(0, 20, 2001)
    opacity = torch.sigmoid(head(1 - torch.exp(-support)))
    assert (opacity[1:] - opacity[:-1] >= -1e-7).all()


def test_opacity_initialisation_is_the_analytic_line():
    head = MonotoneOpacity(slope=10.0, bias=-3.0)
    r = torch.linspace(0, 1, 11)
    assert torch.allclose(head(r), 10 * r - 3)


def test_opacity_head_gives_the_same_logits_with_and_without_a_gradient():
    # without a gradient an untrained head skips its (zero) bend; a trained one must not
    head = MonotoneOpacity()
    r = torch.linspace(0, 1, 101)
    for w in (0.0, 0.7):
        with torch.no_grad():
            head.w.fill_(w)
            fast = head(r)
        traced = head(r)
        assert traced.requires_grad and torch.allclose(fast, traced, atol=1e-6)
    assert not torch.allclose(fast, 30.0 * r, atol=1e-3)  # the bend of w = 0.7 is there


def test_quaternion_round_trip():
    q = torch.randn(200, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    q = q / q.norm(dim=1, keepdim=True)
    R = torch.from_numpy(quaternion_to_matrix(q.numpy()))
    q2 = matrix_to_quaternion(R)
    assert torch.allclose(q2.abs(), q.abs(), atol=1e-9) and ((q2 * q).sum(1).abs() > 1 - 1e-9).all()


def fields_of_planar_voxel(voxel=0.1, thickness=0.0):
    """One voxel whose points spread over the z = const plane (uniform in x, y), +-thickness in z."""
    xs, ys = np.meshgrid(np.linspace(-0.049, 0.049, 9), np.linspace(-0.049, 0.049, 9))
    zs = np.where(np.arange(81) % 2 == 0, thickness, -thickness)
    pts = np.stack([xs.ravel() + 0.05, ys.ravel() + 0.05, zs + 0.05], 1)
    cov = np.cov(pts.T, bias=True)
    return {
        "reliability": torch.tensor([3.0]),
        "features": torch.randn(1, 4),
        "representative_position": torch.tensor([[0.02, 0.03, 0.05]]),  # one of the points
        "position_mean": torch.from_numpy(pts.mean(0)[None]).float(),
        "position_cov": torch.from_numpy(cov[None]).float(),
        "colour": torch.tensor([[0.2, 0.4, 0.6]]),
    }, cov


def test_analytic_initialisation():
    dec = GaussianDecoder(feature_dim=4)
    fields, cov = fields_of_planar_voxel()
    g = dec(fields, voxel_size=0.1)
    # the offset head starts at zero: the mean is the points' centroid, not the representative point
    assert torch.equal(g.means, fields["position_mean"]) and not torch.equal(g.means, fields["representative_position"])
    assert torch.allclose(g.colours, fields["colour"], atol=1e-6)
    logit = OPACITY_SLOPE * (1 - math.exp(-3)) + OPACITY_BIAS  # support 3 typical views, the untrained line
    assert g.opacities.item() == pytest.approx(1 / (1 + math.exp(-logit)), rel=1e-5)
    # smallest axis along the plane normal (clamped thickness); in-plane, points within one voxel never
    # spread past the seam-closing clamp, so both in-plane stds are the clamp
    R = torch.from_numpy(quaternion_to_matrix(g.quats.numpy()))[0]
    normal_axis = R[:, g.scales[0].argmin()]
    assert abs(normal_axis[2].item()) > 0.999
    assert g.scales[0].min().item() == pytest.approx(0.05 * 0.1, rel=1e-5)
    assert math.sqrt(cov[0, 0]) * FOOTPRINT_GAIN < FULL_VOXEL_EXTENT
    assert sorted(g.scales[0].tolist())[1:] == pytest.approx([0.1 * FULL_VOXEL_EXTENT] * 2, rel=1e-4)


def test_zero_heads_are_skipped_without_a_gradient_and_give_the_same_gaussians():
    # the training-free decoder's heads add zeros: a decode skips them (and F_scene, which only they
    # and the features read) for the same values; with a gradient, or once a head is not zero, they run
    dec = GaussianDecoder(feature_dim=4)
    torch.manual_seed(0)
    n = 64
    cov = torch.randn(n, 3, 3) * 0.001
    fields = {"features": torch.randn(n, 4), "position_mean": torch.randn(n, 3), "position_cov": cov @ cov.transpose(1, 2),
              "sh": torch.randn(n, 4, 3), "labels": None}
    with_heads = dec.shapes_and_colours(fields, 0.02)  # gradients on: the heads run
    with torch.no_grad():
        assert dec.heads_add_nothing()
        skipped = dec.shapes_and_colours({k: v for k, v in fields.items() if k != "features"}, 0.02)
    for key in ("means", "scales", "quats", "sh"):
        assert torch.equal(skipped[key], with_heads[key]), key
    assert skipped["features"] is None
    assert not dec.heads_add_nothing()  # a gradient is wanted here: training starts from zero heads
    with torch.no_grad():
        dec.color_delta.bias[0] = 0.1
        assert not dec.heads_add_nothing()
        moved = dec.shapes_and_colours(fields, 0.02)
    assert torch.allclose(moved["sh"][:, 0, 0], with_heads["sh"][:, 0, 0] + 0.1 / SH_C0)


def test_decoded_means_average_the_depth_noise_of_every_fold():
    # a wall through the voxel centres (z = 2.025) seen by 6 frames with independent depth noise (sigma
    # 1/5 voxel): each voxel's Gaussian sits at its points' centroid, closer to the wall than the single
    # representative sample
    voxel, w, h, f = 0.05, 64, 48, 100.0
    rng = np.random.default_rng(0)
    scene = Scene(SceneConfig(voxel_size=voxel, free_space={"enabled": False}))
    for k in range(6):
        c2w = np.eye(4)
        c2w[0, 3] = 0.02 * k
        cam = Camera([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1]], c2w, w, h)
        depth = (2.025 + 0.01 * rng.standard_normal((h, w))).astype(np.float32)
        scene.fold(Frame(rgb=np.full((h, w, 3), 120, np.uint8), camera=cam, depth=depth))
    fields = scene.fields(sort=False)
    many = fields["observations"] >= 20
    means = scene.decode().means
    assert len(means) == len(many) and many.sum() > 100
    err_mean = (means[many, 2] - 2.025).abs().mean().item()
    err_rep = (fields["representative_position"][many, 2] - 2.025).abs().mean().item()
    assert err_mean < 0.5 * err_rep, (err_mean, err_rep)


def test_thickness_is_the_moment_std_times_the_footprint_gain():
    fields, cov = fields_of_planar_voxel(thickness=0.01)  # z std 0.01 (0.1 voxel): above the 0.05 clamp
    g = GaussianDecoder(feature_dim=4)(fields, voxel_size=0.1)
    assert g.scales[0].min().item() == pytest.approx(math.sqrt(cov[2, 2]) * FOOTPRINT_GAIN, rel=1e-4)


def test_support_unit_is_the_median_weight_per_observation():
    assert support_unit(torch.tensor([0.5, 1.0, 3.0, 7.0]), torch.tensor([1, 2, 3, 0])) == pytest.approx(0.5)
    assert support_unit(torch.zeros(0), torch.zeros(0, dtype=torch.int64)) == 1.0  # empty scene: any unit


def test_opacity_is_invariant_to_a_global_reliability_scale():
    # a capture whose every reliability is 10x lower (a noisier sensor) decodes to the same opacities
    dec = GaussianDecoder(feature_dim=4)
    fields, _ = fields_of_planar_voxel()
    fields["reliability"] = torch.tensor([0.02, 0.05, 0.1, 0.2])  # below saturation of the steep default line
    fields = {k: v.expand(4, *v.shape[1:]) if k != "reliability" else v for k, v in fields.items()}
    bright = dec(fields, voxel_size=0.1, support_unit=0.5).opacities
    dim = dec({**fields, "reliability": fields["reliability"] / 10}, voxel_size=0.1, support_unit=0.05).opacities
    assert torch.allclose(bright, dim, atol=1e-6) and (bright[1:] > bright[:-1]).all()
    with pytest.raises(ValueError, match="support_unit"):
        dec(fields, voxel_size=0.1, support_unit=0.0)


def test_scales_are_clamped_to_the_voxel_scale():
    dec = GaussianDecoder(feature_dim=4)
    fields, _ = fields_of_planar_voxel()
    fields["position_cov"] = torch.eye(3)[None] * 10.0  # absurdly wide
    assert dec(fields, voxel_size=0.1).scales.max().item() == pytest.approx(0.1)
    fields["position_cov"] = torch.zeros(1, 3, 3)  # a single observation
    s = dec(fields, voxel_size=0.1).scales[0]
    assert sorted(s.tolist()) == pytest.approx([0.005, 0.1 * FULL_VOXEL_EXTENT, 0.1 * FULL_VOXEL_EXTENT])


@pytest.mark.realdata
def test_level_of_detail_keeps_best_supported(shelf_frames):
    scene = Scene(SceneConfig(voxel_size=0.004))
    for f in shelf_frames[:3]:
        scene.fold(f)
    fields = scene.fields(sort=False)
    support = fields["reliability"]
    full = scene.decode()
    top = scene.decode(max_gaussians=1000)
    surface = (support > 0) & (fields["free_space"] <= scene.config.free_space.dominance * support)
    assert len(full) == int(surface.sum()) < len(support) and len(top) == 1000
    threshold = torch.sort(support, descending=True).values[999]
    assert (scene.decode(min_support=threshold.item()).opacities.numel()) <= 1000
    assert top.opacities.min() >= full.opacities.min()
    with pytest.raises(ValueError, match="max_gaussians"):
        scene.decode(max_gaussians=-1)


@pytest.mark.realdata
def test_opacity_line_settings_move_only_opacity_along_the_line(shelf_frames):
    # the SceneConfig knobs reach the decoder's analytic logit a r + b - penalty(q): a change of b
    # moves every logit by that change, a change of a by that change times r; nothing else moves
    settings = {"default": {}, "bias -3": {"decoder": {"opacity_bias": -3.0}},
                "slope 1": {"decoder": {"opacity_slope": 1.0}}}
    scenes = {k: Scene(SceneConfig(voxel_size=0.004, colour_solve={"views": 0}, **v)) for k, v in settings.items()}
    for scene in scenes.values():
        for f in shelf_frames[:2]:
            scene.fold(f)
    g = {k: s.decode() for k, s in scenes.items()}
    for name in ("means", "scales", "quats", "sh", "features"):
        assert torch.equal(getattr(g["default"], name), getattr(g["bias -3"], name)), name
        assert torch.equal(getattr(g["default"], name), getattr(g["slope 1"], name)), name
    # reference r of every decoded voxel (the decode's keep rule and support unit, module docstring)
    f = scenes["default"].fields(sort=False)
    unit = support_unit(f["reliability"], f["observations"]) * scenes["default"].observations_per_view()
    keep = (f["reliability"] > 0) & (f["free_space"] <= 2.0 * f["reliability"])
    r = (1.0 - torch.exp(-f["reliability"][keep].double() / unit))
    ops = torch.stack([g[k].opacities.double() for k in settings])
    unsaturated = ((ops > 1e-3) & (ops < 0.999)).all(0)
    assert unsaturated.float().mean() > 0.1
    logit = torch.logit(ops[:, unsaturated])
    assert torch.allclose(logit[0] - logit[1], torch.full_like(logit[0], 3.0), atol=1e-3)
    assert torch.allclose(logit[0] - logit[2], 2.0 * r[unsaturated], atol=1e-3)
    assert (g["default"].opacities >= g["bias -3"].opacities).all()
    assert (g["default"].opacities >= g["slope 1"].opacities).all()


def test_default_opacity_line_reads_in_typical_views():
    # the documented reading of the default line (SceneConfig.decoder.opacity_slope): a voxel with next to
    # no support half opaque, one typical view's support 87 %, full support 95 %
    head = MonotoneOpacity()
    r = 1.0 - torch.exp(-torch.tensor([0.0, 1.0, 20.0]))  # support in typical views -> r
    with torch.no_grad():
        alpha = torch.sigmoid(head(r))
    assert torch.allclose(alpha, torch.tensor([0.5, 0.87, 0.95]), atol=0.01)


def test_session_defaults_are_the_decoders_line():
    # SceneConfig stays free of torch, so it repeats the decoder's defaults: they must not drift apart
    config = SceneConfig(voxel_size=0.01)
    assert (config.decoder.opacity_slope, config.opacity_bias) == (OPACITY_SLOPE, OPACITY_BIAS)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf"), True, "steep"])
def test_opacity_slope_setting_rejects_non_positive_numbers(bad):
    with pytest.raises(ValueError, match=r"^decoder\.opacity_slope: "):
        SceneConfig(voxel_size=0.01, decoder={"opacity_slope": bad})


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), True, "high"])
def test_opacity_bias_setting_rejects_non_numbers(bad):
    with pytest.raises(ValueError, match=r"^decoder\.opacity_bias: "):
        SceneConfig(voxel_size=0.01, decoder={"opacity_bias": bad})
