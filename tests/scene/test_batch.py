"""The batch rule against a hand-computed case, and what each ablation mode changes."""

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.scene import aggregate_batch

from ..conftest import make_frame

# One 1x3 frame whose three pixels land in voxel (0, 0, 0) (fx = 10, z = 0.5, voxel 1.0), with
# client features and per-pixel std, so every observation's F and R are known exactly.
FEATS = np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 0.4]], np.float32)
STD = np.array([0.5, 0.2, 0.1], np.float32)
RGB = np.array([[10, 20, 30], [40, 50, 60], [70, 80, 90]], np.uint8)


def tiny_frame():
    return make_frame(np.full((1, 3), 0.5), rgb=RGB[None], features=FEATS[None], depth_std=STD[None], fx=10.0)


def config(mode="full", weight_floor=0.0):  # the paper's rule unless a floor is asked for
    return SceneConfig(voxel_size=1.0, features={"dim": 2, "backend": "client"}, research={"weighting": mode}, sensor={"edge_weight": 0.0, "weight_floor": weight_floor},
                       range={"near": 0.01})


def cos(a, b):
    return a @ b / (np.linalg.norm(a) * np.linalg.norm(b))


def kept(f):  # a representative's feature as the map keeps it: its largest channel scaled to 127, rounded
    return np.floor(f * 127 / np.abs(f).max() + 0.5)


def expected(mode, weight_floor=0.0):
    R = np.exp(-STD.astype(np.float64))  # U_pos = std / voxel_size, U_app = 0
    rsel = R if mode in ("full", "no_similarity") else np.ones(3)
    rep = int(np.argmax(rsel))
    sim = np.array([max(0.0, cos(f, kept(FEATS[rep]))) for f in FEATS]) if mode in ("full", "no_reliability") else np.ones(3)
    W = np.maximum(rsel * sim, weight_floor * rsel[rep])
    return rep, W.sum(), (W[:, None] * FEATS).sum(0) / (W.sum() + 1e-8), (W[:, None] * RGB / 255.0).sum(0) / W.sum()


@pytest.mark.parametrize("weight_floor", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("mode", ["full", "no_reliability", "no_similarity", "average"])
def test_batch_rule_matches_hand_computation(mode, weight_floor):
    f = aggregate_batch([tiny_frame()], config(mode, weight_floor))
    rep, r_scene, f_scene, colour = expected(mode, weight_floor)
    assert f["keys"].numel() == 1
    assert f["reliability"].item() == pytest.approx(r_scene, rel=1e-6)
    assert np.allclose(f["features"][0].numpy(), f_scene, atol=1e-6)
    assert np.allclose(f["colour"][0].numpy(), colour, atol=1e-6)
    assert np.allclose(f["representative_feature"][0].numpy(), kept(FEATS[rep]) / np.linalg.norm(kept(FEATS[rep])))
    assert f["observations"].item() == 3


def test_full_rule_by_hand_numbers():
    # written out once, so the reference itself is pinned: rep = pixel 2 (std 0.1), its feature (1, 0.4)
    # kept as (127, 51) (`stored.quantize_direction`), |(127, 51)| = sqrt(18730)
    f = aggregate_batch([tiny_frame()], config())
    w = [np.exp(-0.5) * 127 / np.sqrt(18730), np.exp(-0.2) * 178 / (np.sqrt(2) * np.sqrt(18730)), np.exp(-0.1)]
    assert f["reliability"].item() == pytest.approx(sum(w), rel=1e-6)


def test_ablations_change_what_they_should():
    full, no_rel, no_sim, avg = (aggregate_batch([tiny_frame()], config(m)) for m in ("full", "no_reliability", "no_similarity", "average"))
    # no_reliability: representative is the first observation, not the most reliable one
    assert np.allclose(no_rel["representative_feature"][0].numpy(), [1.0, 0.0])
    assert np.allclose(full["representative_feature"][0].numpy(), FEATS[2] / np.linalg.norm(FEATS[2]), atol=1 / 127)
    # no_similarity: weights are reliabilities alone
    assert no_sim["reliability"].item() == pytest.approx(np.exp(-STD.astype(np.float64)).sum(), rel=1e-6)
    # average: plain mean, weight 1 per observation
    assert avg["reliability"].item() == pytest.approx(3.0)
    assert np.allclose(avg["features"][0].numpy(), FEATS.mean(0), atol=1e-6)
    assert len({round(x["reliability"].item(), 6) for x in (full, no_rel, no_sim, avg)}) == 4


def test_negative_similarity_gets_zero_weight():
    feats = np.array([[[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]]], np.float32)
    frame = make_frame(np.full((1, 3), 0.5), features=feats, depth_std=STD[None], fx=10.0)
    f = aggregate_batch([frame], config())
    assert f["reliability"].item() == pytest.approx(np.exp(-0.5) + np.exp(-0.1), rel=1e-6)


def test_fields_positions_and_moments():
    f = aggregate_batch([tiny_frame()], config("average"))
    pts = np.array([[0.0, 0, 0.5], [0.05, 0, 0.5], [0.1, 0, 0.5]])
    assert np.allclose(f["position_mean"][0].numpy(), pts.mean(0), atol=1e-6)
    assert np.allclose(f["position_cov"][0].numpy(), np.cov(pts.T, bias=True), atol=1e-6)
    assert torch.equal(f["representative_position"][0], torch.tensor([0.0, 0.0, 0.5]))
