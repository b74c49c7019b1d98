"""Multi-view depth (plane sweep with positional uncertainty): fast paths held to references,
the paper's rule, visibility, the source window and its snapshot. Real-data accuracy is in
test_mvs_shelf.py."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from PIL import Image

from canonical_core import Camera
from canonical_core.datasets import synthetic_rgbd
from canonical_core.evidence import matching
from canonical_core.evidence.matching import (
    MATCH_SHARPNESS,
    MATCHING_FEATURE_DIM,
    dequantize,
    matching_coefficients,
    matching_features,
    matching_features_reference,
)
from canonical_core.eval.mvs_eval import (
    LogitScale,
    compare_to_sensor,
    sparsification,
    stream_depth,
    without_depth,
)
from canonical_core.eval.mvs_preview import write_depth_previews
from canonical_core.evidence.completion import complete_depth, sensor_holes
from canonical_core.evidence.mvs import (
    DepthRefinement,
    IdentityRefinement,
    depth_hypotheses,
    depth_range_from_depth,
    depth_range_from_points,
    estimate_depth,
    estimate_depth_detailed,
    sweep_pixels_for,
    upsample_depth,
)
from canonical_core.evidence.source_views import SelectionRule, SourceView, SourceWindow, select_sources
from canonical_core.evidence.sweep import (
    depth_distribution,
    depth_distribution_reference,
    plane_sweep,
    plane_sweep_reference,
)


@pytest.fixture(scope="module")
def synth():
    """Five exact RGB-D frames at 160x120 (textured boxes), neighbours ~5 cm apart at ~1 m."""
    return list(synthetic_rgbd(num_frames=48, width=160, height=120)[8:13])


def rotated(cam: Camera, yaw_deg: float, shift=(0.0, 0.0, 0.0)) -> Camera:
    a = math.radians(yaw_deg)
    R = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = shift
    return cam.with_pose(cam.c2w64() @ T)


# -- matching features ----------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_matching_features_fast_path_equals_reference(seed):
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(37, 53, 3, generator=g)
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 3, 1, 1)[0].permute(1, 2, 0)  # some structure
    fast = matching_features(img).astype(np.int64)
    ref = matching_features_reference(img).astype(np.int64)
    assert fast.shape == (37, 53, MATCHING_FEATURE_DIM) and fast.dtype == np.int64
    diff = np.abs(fast - ref)
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3  # rounding ties only
    coef = matching_coefficients(img).numpy()
    assert np.abs(fast * matching.MATCHING_QUANT - coef).max() <= matching.MATCHING_QUANT / 2 + 1e-4
    assert np.array_equal(matching_features(img), matching_features(img))  # deterministic


def test_sweep_luminance_is_a_block_average_at_half_resolution():
    rgb = torch.randint(0, 256, (21, 34, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    luma = (rgb.float() / 255) @ torch.tensor([0.299, 0.587, 0.114])
    half = matching.sweep_luminance(rgb, (10, 17))
    expected = torch.nn.functional.avg_pool2d(luma[None, None, :20], 2)[0, 0].numpy()
    assert half.shape == (10, 17) and np.abs(half - expected).max() < 1e-5
    third = matching.sweep_luminance(rgb, (7, 11))
    assert third.shape == (7, 11) and 0 <= third.min() and third.max() <= 1
    assert np.abs(matching.sweep_luminance(rgb, (21, 34)) - luma.numpy()).max() < 1e-6


def test_matching_score_is_sharpness_times_correlation():
    """<F, F> / sqrt(L) = MATCH_SHARPNESS * sum over levels of NCC: a textured patch scores about
    4 * 28 = 112 against itself; a flat patch carries no evidence (features ~0)."""
    img = torch.rand(64, 64, 3, generator=torch.Generator().manual_seed(3))
    F = dequantize(matching_features(img))
    self_score = (F * F).sum(-1) / math.sqrt(MATCHING_FEATURE_DIM)
    levels = len(matching.MATCHING_LEVELS)
    assert abs(float(self_score[32, 32]) - MATCH_SHARPNESS * levels) < 0.05 * MATCH_SHARPNESS * levels
    other = (F[32, 32] * F[10, 50]).sum() / math.sqrt(MATCHING_FEATURE_DIM)
    assert float(other) < 0.5 * float(self_score[32, 32])
    flat = matching_features(torch.full((32, 32, 3), 0.4))
    assert np.abs(flat).max() == 0


def test_depth_hypotheses_are_uniform_in_inverse_depth():
    d = depth_hypotheses(0.5, 4.0, 8)
    assert d[0] == pytest.approx(0.5) and d[-1] == pytest.approx(4.0) and np.all(np.diff(d) > 0)
    assert np.allclose(np.diff(1.0 / d), (1 / 4.0 - 1 / 0.5) / 7)
    for bad in [(0.0, 1.0, 8), (2.0, 1.0, 8), (0.5, 4.0, 1)]:
        with pytest.raises(ValueError):
            depth_hypotheses(*bad)


# -- sweep: fast path vs reference ------------------------------------------------------------
@pytest.mark.parametrize("yaw", [0.0, 25.0])
def test_plane_sweep_fast_path_equals_reference(synth, yaw):
    """Same logits and visibility counts, including hypotheses behind a source or outside it."""
    frames = [dataclasses.replace(f, camera=rotated(f.camera, yaw if i == 2 else 0.0)) for i, f in enumerate(synth[:3])]
    ref = SourceView.from_frame(frames[1], 0.5)
    sources = [SourceView.from_frame(frames[0], 0.5), SourceView.from_frame(frames[2], 0.5)]
    hyps = depth_hypotheses(0.05, 5.0, 12)
    logits, count = plane_sweep(ref, sources, hyps)
    ref_logits, ref_count = plane_sweep_reference(ref, sources, hyps)
    assert logits.shape == (60, 80, 12) and logits.dtype == np.float32
    assert np.array_equal(count, ref_count.permute(1, 2, 0).numpy())
    assert 0 < (count == 0).mean() < 1 or yaw == 0  # some hypotheses unseen when a source looks away
    assert np.abs(logits - ref_logits.permute(1, 2, 0).numpy()).max() < 1e-3
    D, U, mass, valid = depth_distribution(logits, count, hyps)
    lt = torch.from_numpy(logits).permute(2, 0, 1)[None].double()
    ct = torch.from_numpy(count.astype(np.int64)).permute(2, 0, 1)[None]
    Dr, Ur, mr, vr = depth_distribution_reference(lt, ct, torch.from_numpy(hyps))
    assert np.abs(D - Dr[0].numpy()).max() < 1e-9 and np.abs(U - Ur[0].numpy()).max() < 1e-9
    assert np.abs(mass - mr[0].numpy()).max() < 1e-9 and np.array_equal(valid, vr[0].numpy())
    # a mask sweeps only its pixels, exactly as the full sweep there; the rest is unseen and invalid
    mask = np.random.default_rng(6).random((60, 80)) < 0.3
    m_logits, m_count = plane_sweep(ref, sources, hyps, mask)
    assert np.array_equal(m_logits[mask], logits[mask]) and np.array_equal(m_count[mask], count[mask])
    assert not m_count[~mask].any() and not m_logits[~mask].any()
    mD, mU, m_mass, m_valid = depth_distribution(m_logits, m_count, hyps, mask)
    assert np.array_equal(mD[mask], D[mask]) and np.array_equal(m_valid[mask], valid[mask])
    assert not m_valid[~mask].any() and not mD[~mask].any() and not m_mass[~mask].any()
    with pytest.raises(ValueError, match=r"mask: expected a bool array of shape \[60, 80\]"):
        plane_sweep(ref, sources, hyps, mask[:, :10])


def test_moments_follow_the_paper():
    """D = sum P d and U = sqrt(sum P (d - D)^2) with P = softmax(logits), checked by hand."""
    hyps = depth_hypotheses(1.0, 3.0, 3)
    logits = np.array([[[0.0, math.log(3.0), 0.0]]], np.float32)  # P = 0.2, 0.6, 0.2
    count = np.ones((1, 1, 3), np.uint8)
    D, U, mass, valid = depth_distribution(logits, count, hyps)
    P = np.array([0.2, 0.6, 0.2])
    assert D[0, 0] == pytest.approx((P * hyps).sum(), rel=1e-6)
    assert U[0, 0] == pytest.approx(math.sqrt((P * (hyps - (P * hyps).sum()) ** 2).sum()), rel=1e-6)
    assert mass[0, 0] == pytest.approx(1.0) and valid[0, 0]
    count[0, 0, 1] = 0  # the likely hypothesis is unseen: mass 0.4 < 0.5 -> no depth
    assert not depth_distribution(logits, count, hyps)[3][0, 0]


# -- estimate_depth ---------------------------------------------------------------------------
def test_estimate_depth_on_exact_synthetic_frames(synth):
    """At full resolution (such small images leave too little support at half resolution)."""
    ref = without_depth(synth[2])
    kw = dict(near=0.6, far=3.0, num_hypotheses=32, scale=1.0)
    depth, unc = estimate_depth(ref, [synth[0], synth[4]], **kw)
    assert depth.shape == unc.shape == (120, 160) and depth.dtype == unc.dtype == np.float32
    assert np.all(unc >= 0) and np.all(unc[depth == 0] == 0)
    abs_rel, u, coverage = compare_to_sensor(depth, unc, synth[2].depth.numpy())
    assert coverage > 0.95
    assert np.median(abs_rel) < 0.035
    order = np.argsort(u)
    assert np.median(abs_rel[order[: order.size // 2]]) < 0.8 * np.median(abs_rel)
    # sources as Frames or as precomputed SourceViews give the same result
    views = [SourceView.from_frame(without_depth(f), 1.0) for f in (synth[0], synth[4])]
    d2, u2 = estimate_depth(ref, views, **kw)
    assert np.array_equal(depth, d2) and np.array_equal(unc, u2)


def test_pixels_no_source_sees_get_no_depth(synth):
    """A source turned 40 degrees away sees the reference's right part only: the rest gets depth 0."""
    ref = without_depth(synth[2])
    src = dataclasses.replace(synth[2], camera=rotated(synth[2].camera, 40.0, shift=(0.05, 0.0, 0.0)))
    est = estimate_depth_detailed(ref, [src], near=0.4, far=4.0, num_hypotheses=32)
    cam = SourceView.from_frame(ref).camera
    # geometry: which sweep pixels project into the source at some hypothesis
    A = np.linalg.inv(est.sources[0].camera.c2w64()) @ cam.c2w64()
    seen_any = np.zeros((cam.height, cam.width), bool)
    v, u = np.mgrid[0: cam.height, 0: cam.width]
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, float)], -1)
    sc = est.sources[0].camera
    for d in est.hypotheses:
        p = rays * d @ A[:3, :3].T + A[:3, 3]
        x, y = p[..., 0] / p[..., 2] * sc.fx + sc.cx, p[..., 1] / p[..., 2] * sc.fy + sc.cy
        seen_any |= (p[..., 2] > 0) & (x >= 0) & (x <= sc.width - 1) & (y >= 0) & (y <= sc.height - 1)
    assert 0.2 < seen_any.mean() < 0.8
    assert np.all(est.sweep_depth[~seen_any] == 0) and np.all(est.sweep_uncertainty[~seen_any] == 0)
    # the upsampled map: the unseen left part is empty, pixels deep inside the seen part are not
    assert np.all(est.depth[:, :10] == 0)
    away = dataclasses.replace(synth[2], camera=rotated(synth[2].camera, 180.0))
    d, u = estimate_depth(ref, [away], near=0.4, far=4.0, num_hypotheses=16)
    assert np.all(d == 0) and np.all(u == 0)


def test_estimate_depth_rejects_bad_input(synth):
    with pytest.raises(ValueError, match="sources"):
        estimate_depth(synth[0], [], near=0.4, far=4.0)
    with pytest.raises(ValueError, match="sources"):
        estimate_depth(synth[0], synth[1], near=0.4, far=4.0)
    with pytest.raises(ValueError, match="sources\\[0\\]"):
        estimate_depth(synth[0], [np.zeros(3)], near=0.4, far=4.0)
    with pytest.raises(ValueError, match="near"):
        estimate_depth(synth[0], [synth[1]], near=2.0, far=1.0)


# -- learned refinement hook ------------------------------------------------------------------
def test_refinement_hook_identity_by_default_and_applied_before_softmax(synth):
    ref, srcs = without_depth(synth[2]), [synth[0], synth[4]]
    kw = dict(near=0.4, far=4.0, num_hypotheses=24)
    base = estimate_depth_detailed(ref, srcs, **kw)
    ident = estimate_depth_detailed(ref, srcs, refine=IdentityRefinement(), **kw)
    assert np.array_equal(base.depth, ident.depth)
    torch_path = estimate_depth_detailed(ref, srcs, refine=LogitScale(1.0), **kw)  # goes through PyTorch
    assert np.abs(torch_path.sweep_depth - base.sweep_depth).max() < 1e-5
    assert np.abs(torch_path.sweep_uncertainty - base.sweep_uncertainty).max() < 1e-5
    seen = {}

    def spy(logits, hypotheses, features):
        seen.update(logits=tuple(logits.shape), hyps=tuple(hypotheses.shape), feats=tuple(features.shape))
        return torch.zeros_like(logits)  # no evidence: P uniform over hypotheses

    assert isinstance(spy, DepthRefinement)
    flat = estimate_depth_detailed(ref, srcs, refine=spy, **kw)
    assert seen == {"logits": (1, 24, 60, 80), "hyps": (24,), "feats": (1, MATCHING_FEATURE_DIM, 60, 80)}
    h = flat.hypotheses
    valid = flat.sweep_depth > 0
    assert np.allclose(flat.sweep_depth[valid], h.mean(), rtol=1e-5)
    assert np.allclose(flat.sweep_uncertainty[valid], h.std(), rtol=1e-5)
    with pytest.raises(ValueError, match="refine"):
        estimate_depth(ref, srcs, refine=lambda lg, hy, ft: lg[:, :3], **kw)


# -- upsampling -------------------------------------------------------------------------------
def test_upsampling_interpolates_smooth_depth_but_not_across_edges():
    d = np.full((6, 8), 2.0, np.float32)
    d[:, 4:] = 1.0  # a depth edge
    d[0, 0] = 0.0  # a missing pixel
    u = np.full_like(d, 0.01)
    D, U = upsample_depth(d, u, (12, 16))
    assert D.shape == (12, 16) and D.dtype == np.float32
    assert set(np.unique(D)) <= {0.0, 1.0, 2.0}  # nothing in between: no flying depths on the edge
    assert np.all(D[:2, :2] == 0) and np.all(U[D == 0] == 0)
    ramp = np.tile(np.linspace(1.0, 1.1, 8, dtype=np.float32), (6, 1))
    D, _ = upsample_depth(ramp, u, (12, 16))
    assert len(np.unique(D)) > 8  # interpolated where smooth


# -- choosing and keeping sources -------------------------------------------------------------
def line_cameras(xs, yaw=0.0):
    K = [[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]]
    return [rotated(Camera(K, np.eye(4), 80, 60), yaw, shift=(x, 0.0, 0.0)) for x in xs]


def test_select_sources_prefers_the_target_baseline_and_spreads_picks():
    ref = line_cameras([0.0])[0]
    xs = [0.0, 0.01, -0.08, 0.16, 0.17, 0.5, -0.15]  # at 1 m: ratios 0, .01, .08, .16, .17, .5, .15
    cams = line_cameras(xs)
    picks = select_sources(ref, cams, k=2, depth=1.0)
    assert picks[0] == 3  # ratio 0.16 = target
    assert picks[1] == 6  # the other side (0.15) beats 0.17, which is next to the first pick
    eligible = select_sources(ref, cams, k=4, depth=1.0)
    assert sorted(eligible) == [2, 3, 4, 6]  # not 1 (ratio below min_ratio) nor 5 (beyond max_ratio)...
    everything = select_sources(ref, cams, k=7, depth=1.0)
    assert everything[:4] == eligible and sorted(everything[4:]) == [1, 5]  # ...which only fill what is left
    assert 0 not in everything  # no baseline: never
    assert select_sources(ref, line_cameras([0.0, 0.01]), k=2, depth=1.0) == [1]  # fallback: best there is
    turned = [rotated(c, 60.0) for c in cams]
    assert select_sources(ref, turned, k=2, depth=1.0) == []  # too oblique / no overlap


def test_select_sources_fills_a_sparse_stream_with_a_wider_baseline():
    # A stream whose views are 0.17 apart at 1 m: the view two back (0.34) is beyond max_ratio (0.3),
    # yet as a second source it beats none; it never displaces an eligible one.
    ref = line_cameras([0.0])[0]
    assert select_sources(ref, line_cameras([-0.34, -0.17]), k=2, depth=1.0) == [1, 0]
    assert select_sources(ref, line_cameras([-0.34, -0.17]), k=1, depth=1.0) == [1]
    assert sorted(select_sources(ref, line_cameras([-0.34, -0.17, 0.15]), k=2, depth=1.0)) == [1, 2]


def tiny_view(cam: Camera, fid: str, depth=1.0, fill=0) -> SourceView:
    return SourceView(camera=cam, features=np.full((cam.height, cam.width, 4), fill, np.int8), frame_id=fid,
                      median_depth=depth)


def test_source_window_keeps_a_bounded_spread_of_views():
    win = SourceWindow(capacity=3)
    cams = line_cameras([0.01 * i for i in range(30)])
    for i, cam in enumerate(cams):
        win.add(tiny_view(cam, str(i)))
        assert len(win) <= 3
    ids = [int(v.frame_id) for v in win]
    assert ids[-1] == 29  # the newest is always kept
    assert min(ids) <= 29 - 10  # older views survive: baselines up to the rule's range, not the last 3 frames
    assert all(0.01 * (29 - i) <= SelectionRule().max_ratio + 1e-9 for i in ids)  # out-of-reach views evicted
    assert win.nbytes == sum(v.features.nbytes for v in win)
    sel = win.select(tiny_view(line_cameras([0.3])[0], "next"), k=2)
    assert 1 <= len(sel) <= 2 and all(isinstance(v, SourceView) for v in sel)


def test_source_window_snapshot_round_trip(tmp_path, synth):
    win = SourceWindow(capacity=2, rule=SelectionRule(target_ratio=0.1), default_depth=0.8)
    for f in synth[:3]:
        win.add(without_depth(f), depth=f.depth)
    arrays = win.to_arrays()
    assert all(isinstance(a, np.ndarray) for a in arrays.values())
    np.savez(tmp_path / "w.npz", **arrays)
    with np.load(tmp_path / "w.npz", allow_pickle=False) as z:
        back = SourceWindow.from_arrays(z)
    assert len(back) == len(win) == 2 and back.capacity == 2 and back.rule == win.rule
    for a, b in zip(win, back):
        assert np.array_equal(a.features, b.features) and a.frame_id == b.frame_id
        assert np.array_equal(a.camera.c2w64(), b.camera.c2w64()) and np.array_equal(a.camera.K64(), b.camera.K64())
        assert a.median_depth == b.median_depth and a.scale == b.scale
    ref = without_depth(synth[3])
    assert [v.frame_id for v in win.select(ref)] == [v.frame_id for v in back.select(ref)]
    d1, u1 = estimate_depth(ref, win.select(ref), near=0.4, far=4.0, num_hypotheses=16)
    d2, u2 = estimate_depth(ref, back.select(ref), near=0.4, far=4.0, num_hypotheses=16)
    assert np.array_equal(d1, d2) and np.array_equal(u1, u2)
    empty = SourceWindow.from_arrays(SourceWindow().to_arrays())
    assert len(empty) == 0
    broken = dict(arrays)
    del broken["features"]
    with pytest.raises(ValueError, match="features"):
        SourceWindow.from_arrays(broken)
    for change, message in (({"version": np.array(2)}, "^version: unsupported source-window format 2"),
                            ({"features": arrays["features"][:-1]}, "^features: expected .* int8 values"),
                            ({"features": arrays["features"].astype(np.int16)}, "^features: expected .* int8 values"),
                            ({"capacity": np.array(1)}, "^capacity: 2 views exceed the capacity 1")):
        with pytest.raises(ValueError, match=message):
            SourceWindow.from_arrays(arrays | change)


def test_stream_folds_every_frame_and_the_first_after_its_partner(synth):
    results = stream_depth(synth[:4], num_sources=2, near=0.4, far=4.0, num_hypotheses=16, scale=0.5)
    assert [r.index for r in results] == [1, 0, 2, 3]  # frame 0 waited for frame 1
    assert results[1].sources == [synth[1].frame_id]
    assert all(r.coverage > 0.5 for r in results)


# -- ranges, metrics, pictures ----------------------------------------------------------------
def test_depth_range_helpers():
    cam = line_cameras([0.0])[0]
    z = np.linspace(0.5, 2.0, 200)
    pts = np.stack([np.zeros_like(z), np.zeros_like(z), z], -1)
    near, far = depth_range_from_points(cam, pts, margin=0.0, low=0, high=100)
    assert near == pytest.approx(0.5) and far == pytest.approx(2.0)
    assert depth_range_from_points(cam, pts[:10]) is None  # too few points seen
    assert depth_range_from_points(cam, -pts) is None  # behind the camera
    near, far = depth_range_from_depth(np.full((20, 20), 1.0))
    assert near < 1.0 < far


def test_sparsification_and_ause():
    rng = np.random.default_rng(0)
    e = rng.random(1000)
    perfect = sparsification(e, e)
    assert perfect["ause"] == pytest.approx(0.0, abs=1e-12) and perfect["monotone"]
    noisy = sparsification(e, e + rng.random(1000))
    random = sparsification(e, rng.random(1000))
    assert 0 < noisy["ause"] < random["ause"]


def test_write_depth_previews(tmp_path, synth):
    records = write_depth_previews(synth[:3], tmp_path / "out", num_sources=2, near=0.4, far=4.0, num_hypotheses=16)
    assert len(records) == 3
    for r in records:
        for key in ("depth_png", "uncertainty_png", "sensor_png"):
            with Image.open(r[key]) as im:
                assert im.size[1] == 120 and im.size[0] > 160  # map + legend
        assert r["coverage"] > 0.5 and r["median_abs_rel"] < 0.2
    no_depth = [without_depth(f) for f in synth[:2]]
    records = write_depth_previews(no_depth, tmp_path / "rgb", near=0.4, far=4.0, num_hypotheses=16)
    assert records[0]["sensor_png"] is None and "median_abs_rel" not in records[0]
    with pytest.raises(ValueError, match="frames"):
        write_depth_previews(no_depth[:1], tmp_path / "one")


def test_source_view_validation(synth):
    cam = synth[0].camera
    with pytest.raises(ValueError, match="features"):
        SourceView(camera=cam, features=np.zeros((120, 160, 4), np.float32))
    with pytest.raises(ValueError, match="features"):
        SourceView(camera=cam, features=np.zeros((10, 10, 4), np.int8))
    with pytest.raises(ValueError, match="scale"):
        SourceView.from_frame(synth[0], scale=0.0)
    v = SourceView.from_frame(synth[0], 0.25)
    assert v.features.shape == (30, 40, MATCHING_FEATURE_DIM) and v.camera.width == 40
    assert math.isfinite(v.median_depth)  # from the frame's depth
    assert math.isnan(SourceView.from_frame(without_depth(synth[0])).median_depth)


def test_sensor_holes_are_pixels_beyond_the_radius_of_any_measured_pixel():
    rng = np.random.default_rng(3)
    depth = np.where(rng.random((30, 40)) < 0.02, 0.5, 0.0).astype(np.float32)  # sparse measured pixels
    depth[5:20, 5:25] = rng.uniform(0.3, 0.6, (15, 20))
    v, u = np.mgrid[:30, :40]
    measured_v, measured_u = np.nonzero(depth > 0)
    # Chebyshev distance to the nearest measured pixel, by brute force
    dist = np.min(np.maximum(np.abs(v[..., None] - measured_v), np.abs(u[..., None] - measured_u)), axis=-1)
    for radius in (1, 3, 7):
        assert np.array_equal(sensor_holes(depth, radius), dist > radius)
    assert sensor_holes(np.zeros((4, 6), np.float32), 2).all()


@pytest.mark.parametrize("radius", [0, True, 1.5])
def test_sensor_holes_rejects_bad_radius(radius):
    with pytest.raises(ValueError, match="radius: expected a positive integer"):
        sensor_holes(np.zeros((4, 6), np.float32), radius)


def test_complete_depth_fills_only_holes_the_sweep_has_depth_for():
    rng = np.random.default_rng(3)
    depth = np.zeros((30, 40), np.float32)
    depth[5:20, 5:25] = rng.uniform(0.3, 0.6, (15, 20))
    depth[10, 10] = 0.0  # a small hole inside the measured region
    estimate = rng.uniform(0.5, 1.0, depth.shape).astype(np.float32)
    estimate[25:, :] = 0.0  # the sweep has no depth here
    std, unc = np.full_like(depth, 0.002), np.full_like(depth, 0.05)
    holes = sensor_holes(depth, 3)
    out, out_std, filled = complete_depth(depth, std, estimate, unc, holes)
    assert np.array_equal(filled, holes & (estimate > 0))
    assert not filled[10, 10] and out[10, 10] == 0.0  # small holes stay holes
    assert np.array_equal(out[depth > 0], depth[depth > 0]) and np.array_equal(out_std[depth > 0], std[depth > 0])
    assert np.array_equal(out[filled], estimate[filled]) and np.all(out_std[filled] == 0.05)
    assert np.all(out[~filled & (depth == 0)] == 0.0)
    # a hole mask that covers measured pixels never changes them
    out, out_std, filled = complete_depth(depth, std, estimate, unc, np.ones_like(holes))
    assert np.array_equal(out[depth > 0], depth[depth > 0]) and not filled[depth > 0].any()


@pytest.mark.parametrize("change, message", [
    ({"estimate": np.zeros((4, 5), np.float32)}, r"estimate: expected shape \[4, 6\]"),
    ({"depth_std": np.zeros((6, 4), np.float32)}, r"depth_std: expected shape \[4, 6\]"),
    ({"holes": np.zeros((4, 5), bool)}, r"holes: expected shape \[4, 6\]"),
    ({"holes": np.zeros((4, 6), np.float32)}, "holes: expected a bool array, got float32"),
])
def test_complete_depth_rejects_bad_input(change, message):
    args = {name: np.zeros((4, 6), np.float32) for name in ("depth", "depth_std", "estimate", "uncertainty")}
    with pytest.raises(ValueError, match=message):
        complete_depth(**(args | {"holes": np.ones((4, 6), bool)} | change))


@pytest.mark.parametrize("image, sweep", [((48, 64), (24, 32)), ((30, 40), (11, 17)), ((8, 8), (8, 8))])
def test_sweep_pixels_for_are_all_that_upsampling_reads_at_the_wanted_pixels(image, sweep):
    rng = np.random.default_rng(4)
    where = rng.random(image) < 0.05
    needed = sweep_pixels_for(where, sweep)
    assert needed.sum() <= 4 * where.sum() and needed.mean() < 0.9  # at most the 4 taps of each pixel
    for trial in range(5):  # any sweep map, with holes and depth edges: blanking the rest changes nothing there
        depth = rng.uniform(0.5, 3.0, sweep).astype(np.float32) * (rng.random(sweep) < 0.8)
        unc = rng.uniform(0.0, 0.1, sweep).astype(np.float32)
        full_d, full_u = upsample_depth(depth, unc, image)
        part_d, part_u = upsample_depth(np.where(needed, depth, 0), np.where(needed, unc, 0), image)
        assert np.array_equal(part_d[where], full_d[where]) and np.array_equal(part_u[where], full_u[where])


def test_estimate_depth_where_matches_the_full_sweep_there(synth):
    ref, srcs = without_depth(synth[2]), [synth[0], synth[4]]
    kw = dict(near=0.4, far=4.0, num_hypotheses=24)
    full_d, full_u = estimate_depth(ref, srcs, **kw)
    where = np.zeros((ref.height, ref.width), bool)
    where[:, :30] = True  # a band, and scattered pixels
    where[np.random.default_rng(5).random(where.shape) < 0.02] = True
    d, u = estimate_depth(ref, srcs, where=where, **kw)
    assert np.array_equal(d[where], full_d[where]) and np.array_equal(u[where], full_u[where])
    assert (d[~where] == 0).mean() > 0.5  # most of the rest was never swept
    with pytest.raises(ValueError, match=r"where: expected a bool array of shape \[120, 160\]"):
        estimate_depth(ref, srcs, where=where[:, :10], **kw)
    with pytest.raises(ValueError, match="where: expected a bool array"):
        estimate_depth(ref, srcs, where=where.astype(np.float32), **kw)
