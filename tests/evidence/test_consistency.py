"""Consecutive frames' depth compared by depth band (`evidence.consistency`): counts against a numpy
reference, the rule that reads a sensor's unmeasurable range, the warning a stream gets, and the real
captures (the labels bin's near-range depth is flagged; the mask bin's, the shelf's are not)."""

from __future__ import annotations

import numpy as np
import pytest

from canonical_core import Camera, Frame, Scene, SceneConfig
from canonical_core.datasets import load_dataset
from canonical_core.evidence import DepthConsistency, compare_depth, inconsistent_below
from canonical_core.evidence.consistency import (AGREE_M, AGREE_REL, BANDS, MIN_COMPARED, STRIDE, band_edge,
                                                 band_of)

F, W, H = 100.0, 160, 120
PLATE = 0.12  # metres: the near object of the synthetic streams


def camera(x: float) -> Camera:
    c2w = np.eye(4)
    c2w[0, 3] = x
    return Camera(K=[[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]], c2w=c2w, width=W, height=H)


def wall_and_plate(x: float, plate: str) -> np.ndarray:
    """Depth of a fronto-parallel wall at 1 m seen from (x, 0, 0), and a near patch at `PLATE` m:
    ``world`` a plate fixed in the world (x in [-0.03, 0.03], y in [-0.03, 0.03]), ``image`` a patch fixed
    in the image whose depth changes from frame to frame (a sensor's reading, not a surface), ``none``."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    depth = np.ones((H, W), np.float32)
    if plate == "world":
        wx, wy = x + (u - W / 2) / F * PLATE, (v - H / 2) / F * PLATE
        depth[(np.abs(wx) < 0.03) & (np.abs(wy) < 0.03)] = PLATE
    elif plate == "image":
        depth[:, : W // 2] = PLATE + 0.03 * (round(x / 0.01) % 2)  # 0.12 and 0.15 m in turn
    return depth


def stream(plate: str, frames: int = 6) -> list[Frame]:
    rgb = np.full((H, W, 3), 128, np.uint8)
    return [Frame(rgb=rgb, camera=camera(0.01 * k), depth=wall_and_plate(0.01 * k, plate)) for k in range(frames)]


def compare_reference(frame: Frame, previous: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The comparison in plain numpy, float64: every STRIDE-th pixel lifted, moved, projected, compared."""
    sampled, compared, agreed = (np.zeros(BANDS, np.int64) for _ in range(3))
    depth, prev = frame.depth.numpy(), previous.depth.numpy()
    K, Kp = frame.camera.K64(), previous.camera.K64()
    to_prev = np.linalg.inv(previous.camera.c2w64()) @ frame.camera.c2w64()
    for v in range(0, depth.shape[0], STRIDE):
        for u in range(0, depth.shape[1], STRIDE):
            z = float(depth[v, u])
            if not z > 0:
                continue
            b = band_of(z)
            sampled[b] += 1
            p = to_prev[:3, :3] @ np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z]) + to_prev[:3, 3]
            if not p[2] > 0:
                continue
            pu = int(np.floor(Kp[0, 0] * p[0] / p[2] + Kp[0, 2] + 0.5))
            pv = int(np.floor(Kp[1, 1] * p[1] / p[2] + Kp[1, 2] + 0.5))
            if not (0 <= pu < prev.shape[1] and 0 <= pv < prev.shape[0]) or not prev[pv, pu] > 0:
                continue
            compared[b] += 1
            agreed[b] += abs(float(prev[pv, pu]) - p[2]) <= max(AGREE_M, AGREE_REL * p[2])
    return sampled, compared, agreed


def test_bands_start_at_their_edges():
    assert [band_of(band_edge(b)) for b in range(BANDS)] == list(range(BANDS))
    assert [band_of(band_edge(b) * 0.999) for b in range(1, BANDS)] == list(range(BANDS - 1))
    assert band_of(0.0) == 0 and band_of(1e6) == BANDS - 1


def test_the_comparison_equals_the_reference():
    rng = np.random.default_rng(3)
    depth = (0.3 + 2.0 * rng.random((H, W))).astype(np.float32)
    depth[rng.random((H, W)) < 0.3] = 0.0  # holes in both frames
    prev_depth = depth.copy()
    prev_depth[rng.random((H, W)) < 0.3] = 0.0
    prev_depth[:40] += 0.05  # some comparisons disagree
    rgb = np.zeros((H, W, 3), np.uint8)
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[np.cos(0.1), 0, np.sin(0.1)], [0, 1, 0], [-np.sin(0.1), 0, np.cos(0.1)]])
    c2w[:3, 3] = [0.05, -0.02, 0.01]
    frame = Frame(rgb=rgb, camera=Camera(K=[[F, 0, 80], [0, F, 60], [0, 0, 1]], c2w=c2w, width=W, height=H), depth=depth)
    previous = Frame(rgb=rgb, camera=camera(0.0), depth=prev_depth)
    got, want = compare_depth(frame, previous), compare_reference(frame, previous)
    for g, w in zip(got, want):
        assert np.array_equal(g, w)
    sampled, compared, agreed = got
    assert sampled.sum() == (depth[::STRIDE, ::STRIDE] > 0).sum() and 0 < agreed.sum() < compared.sum() < sampled.sum()


def test_a_surface_seen_twice_agrees_and_a_changing_reading_does_not():
    world = stream("world", 2)
    sampled, compared, agreed = compare_depth(world[1], world[0])
    plate = band_of(PLATE)
    assert agreed[plate] == compared[plate] > 0
    assert agreed.sum() >= 0.97 * compared.sum()  # the wall disagrees only where the plate's edge hides it
    image = stream("image", 2)
    sampled, compared, agreed = compare_depth(image[1], image[0])
    near = band_of(PLATE + 0.03)  # frame 1 reads the patch at 0.15 m, frame 0 at 0.12 m
    assert compared[near] > 0 and agreed[near] == 0 and agreed[band_of(1.0)] == compared[band_of(1.0)] > 0


def test_the_rule_needs_disagreement_below_and_agreement_beyond():
    compared, agreed = np.zeros(BANDS, np.int64), np.zeros(BANDS, np.int64)
    assert inconsistent_below(compared, agreed) is None  # nothing measured
    compared[[5, 12]] = MIN_COMPARED
    agreed[[5, 12]] = [0, MIN_COMPARED]
    assert inconsistent_below(compared, agreed) == 5
    agreed[12] = MIN_COMPARED // 2  # beyond it the frames disagree too: poses or depth, not a range
    assert inconsistent_below(compared, agreed) is None
    agreed[12], compared[5] = MIN_COMPARED, MIN_COMPARED - 1  # too few comparisons to say
    assert inconsistent_below(compared, agreed) is None
    compared[5], compared[12] = MIN_COMPARED, 0  # nothing beyond to compare with
    assert inconsistent_below(compared, agreed) is None


def test_a_stream_is_warned_about_readings_that_change_and_not_about_a_near_surface():
    tracker = DepthConsistency()
    warnings = [tracker.observe(f) for f in stream("image")]
    assert warnings[0] == [] and all(warnings[1:])  # the first frame has nothing to compare with
    assert f"range.near={tracker.limit():.2f}" in warnings[-1][0] and tracker.limit() >= band_edge(band_of(PLATE + 0.03) + 1)
    assert warnings[-1][0].startswith("depth: 50% ") and "under the sensor's working range" in warnings[-1][0]
    for plate in ("world", "none"):
        tracker = DepthConsistency()
        assert not any(tracker.observe(f) for f in stream(plate))


def test_after_a_rollback_the_next_frame_is_compared_with_none():
    tracker = DepthConsistency()
    frames = stream("image", 3)
    tracker.observe(frames[0])
    tracker.observe(frames[1])
    counts = tracker.compared.copy()
    tracker.forget_previous()
    assert tracker.observe(frames[2]) == [] and np.array_equal(tracker.compared, counts)


def test_the_fold_report_carries_the_warning_and_the_scene_is_unchanged():
    frames = stream("image")
    scene, reports = Scene(SceneConfig(voxel_size=0.01)), []
    for f in frames:
        reports.append(scene.fold(f))
    assert any("working range" in w for w in reports[-1].warnings)
    # the same frames one at a time into fresh scenes that never compare (a new tracker each): same state
    other = Scene(SceneConfig(voxel_size=0.01))
    for f in frames:
        other._consistency = DepthConsistency()
        other.fold(f)
    assert other.digest() == scene.digest()


@pytest.mark.parametrize("capture, flagged", [("bin_labels", True), ("bin_mask", False)])
def test_the_bins_near_range_depth(apc_bins_path, capture, flagged):
    tracker = DepthConsistency()
    warned = [w for f in load_dataset(apc_bins_path / capture) for w in tracker.observe(f)]
    assert bool(warned) == flagged
    if flagged:  # the labels bin's readings from 0.09 to 0.2 m land elsewhere in every frame
        top = inconsistent_below(tracker.compared, tracker.agreed)
        assert 0.1 < band_edge(top + 1) <= 0.2
        # the limit is where frames are seen to agree: past the bands too thinly sampled to tell (the
        # foam's last readings), under the bin's floor
        assert 0.2 < tracker.limit() <= 0.25 and f"range.near={tracker.limit():.2f}" in warned[-1]
        again = DepthConsistency()  # with the advice taken, nothing more to say
        assert not any(again.observe(f, near=tracker.limit()) for f in load_dataset(apc_bins_path / capture))
        assert again.limit() is None


def test_the_shelf_is_not_flagged(shelf_frames):
    tracker = DepthConsistency()
    assert not any(tracker.observe(f) for f in shelf_frames)


def test_the_limit_is_in_the_stats_and_a_snapshot_keeps_the_counts():
    frames = stream("image")
    scene = Scene(SceneConfig(voxel_size=0.01))
    for f in frames[:4]:
        scene.fold(f)
    limit = scene.stats()["inconsistent_depth_below"]
    assert limit == scene._consistency.limit() and limit >= band_edge(band_of(PLATE + 0.03) + 1)
    restored = Scene.from_bytes(scene.to_bytes())
    assert restored.stats()["inconsistent_depth_below"] == limit and restored.digest() == scene.digest()
    assert np.array_equal(restored._consistency.compared, scene._consistency.compared)
    # the restored stream compares its next frame with none, then goes on counting
    assert restored.fold(frames[4]).warnings == [] and restored.fold(frames[5]).warnings
    assert Scene(SceneConfig(voxel_size=0.01)).stats()["inconsistent_depth_below"] is None


def test_counts_that_do_not_add_up_are_refused():
    tracker = DepthConsistency.from_arrays({})
    assert tracker.limit() is None and not tracker.compared.any()
    good = {"compared": np.full(BANDS, 5, np.int64), "agreed": np.full(BANDS, 2, np.int64)}
    assert np.array_equal(DepthConsistency.from_arrays(good).agreed, good["agreed"])
    for bad in ({**good, "agreed": np.full(BANDS, 6, np.int64)}, {**good, "agreed": -good["agreed"]},
                {**good, "compared": good["compared"][:-1]}, {**good, "compared": good["compared"] * 1.0},
                {"compared": good["compared"]}):
        with pytest.raises(ValueError, match="^consistency: "):
            DepthConsistency.from_arrays(bad)
