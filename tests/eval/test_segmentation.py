"""The segmentation experiment: metrics against hand-computed values, fused labels on a generated
scene, the linear probe, method settings, the client-feature path, error paths and the CLI on a
small real subset."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from canonical_core import SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.datasets.sequence import FrameSequence
from canonical_core.eval.baselines import gaussian_merge, pixel_aligned
from canonical_core.eval.cli import main
from canonical_core.eval.methods import configured
from canonical_core.eval.segmentation import (fit_probe, find_bins, label_confusion, label_map, parse_label_method, probe_confusion,
                                              render_labels, scores, segmentation_split)

VOXEL = 0.03


def box_labels(frame):
    """Two classes from the geometry: 1 on the boxes (world z above 1 cm), 0 on the ground and sky."""
    H, W = frame.height, frame.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    cam, d = frame.camera, frame.depth.numpy().astype(np.float64)
    rays = np.stack([(u - cam.cx) / cam.fx * d, (v - cam.cy) / cam.fy * d, d], -1)
    world = rays @ cam.c2w64()[:3, :3].T + cam.c2w64()[:3, 3]
    box = (d > 0) & (world[..., 2] > 0.01)
    return np.stack([~box, box], -1).astype(np.float32)


@pytest.fixture(scope="module")
def labelled_frames():
    return [replace(f, labels=box_labels(f)) for f in synthetic_rgbd(num_frames=6, width=64, height=48)]


# -- metrics ---------------------------------------------------------------------------------------
def test_scores_match_hand_computed_values_with_an_absent_class_and_uncovered_pixels():
    gt = torch.tensor([[0, 0, 1], [1, 1, 0]])
    pred = torch.tensor([[0, 1, 1], [-1, 1, 2]])  # class 2 is never true; one pixel uncovered
    conf = label_confusion(gt, pred, 3)
    assert conf.tolist() == [[1, 1, 1, 0], [0, 2, 0, 1], [0, 0, 0, 0]]
    s = scores(conf)
    # class 0: TP 1, FP 0, FN 2 -> 1/3; class 1: TP 2, FP 1, FN 1 -> 2/4; class 2: TP 0, FP 1 -> 0
    assert s["iou"] == pytest.approx([1 / 3, 1 / 2, 0.0])
    assert s["miou"] == pytest.approx((1 / 3 + 1 / 2 + 0.0) / 3)
    assert s["accuracy"] == pytest.approx(3 / 6)
    covered = scores(label_confusion(gt, pred, 3, pred >= 0))  # the uncovered pixel leaves the count
    assert covered["accuracy"] == pytest.approx(3 / 5) and covered["iou"][1] == pytest.approx(2 / 3)
    # a class in neither ground truth nor prediction is left out of the mean
    only = scores(label_confusion(torch.tensor([[0, 1]]), torch.tensor([[0, 1]]), 4))
    assert only["iou"] == [1.0, 1.0, None, None] and only["miou"] == 1.0


def test_empty_predictions_score_zero_and_no_pixels_score_none():
    gt = torch.tensor([[0, 1], [1, 1]])
    s = scores(label_confusion(gt, torch.full((2, 2), -1), 2))
    assert s["accuracy"] == 0.0 and s["miou"] == 0.0 and s["iou"] == [0.0, 0.0]
    nothing = scores(label_confusion(gt, torch.full((2, 2), -1), 2, torch.zeros(2, 2, dtype=torch.bool)))
    assert nothing == {"miou": None, "accuracy": None, "iou": [None, None]}


@pytest.mark.parametrize("gt, pred, classes, field", [
    (torch.zeros(2, 3, dtype=torch.long), torch.zeros(3, 2, dtype=torch.long), 2, "pred"),
    (torch.full((2, 2), 2), torch.zeros(2, 2, dtype=torch.long), 2, "gt"),
    (torch.zeros(2, 2, dtype=torch.long), torch.full((2, 2), -2), 2, "pred"),
    (torch.zeros(2, 2, dtype=torch.long), torch.zeros(2, 2, dtype=torch.long), 0, "classes"),
])
def test_label_confusion_rejects_bad_inputs_naming_the_field(gt, pred, classes, field):
    with pytest.raises(ValueError, match=f"^{field}:"):
        label_confusion(gt, pred, classes)
    with pytest.raises(ValueError, match="^mask:"):
        label_confusion(torch.zeros(2, 2, dtype=torch.long), torch.zeros(2, 2, dtype=torch.long), 2,
                        torch.ones(3, 3, dtype=torch.bool))


def test_label_map_looks_up_a_coarser_map_nearest_and_needs_labels(labelled_frames):
    frame = labelled_frames[0]
    coarse = torch.zeros(2, 2, 3)
    coarse[0, 1, 2] = coarse[1, 0, 1] = 1.0  # top-right: 2, bottom-left: 1, rest 0
    ids = label_map(replace(frame, labels=coarse))
    assert ids.shape == (48, 64)
    assert ids[:24, 32:].eq(2).all() and ids[24:, :32].eq(1).all() and ids[:24, :32].eq(0).all()
    with pytest.raises(ValueError, match="^labels:"):
        label_map(replace(frame, labels=None))


# -- the split -------------------------------------------------------------------------------------
def test_segmentation_split_holds_out_every_third_frame_and_spreads_inputs_over_the_rest():
    split = segmentation_split(15, [2, 4, 8])
    assert split.heldout == (1, 4, 7, 10, 13)
    assert split.inputs == {2: (0, 14), 4: (0, 5, 9, 14), 8: (0, 2, 5, 6, 8, 9, 12, 14)}
    for inputs in split.inputs.values():
        assert not set(inputs) & set(split.heldout)
    with pytest.raises(ValueError, match="^views:"):
        segmentation_split(15, [11])
    with pytest.raises(ValueError, match="^heldout_every:"):
        segmentation_split(15, [2], every=1)


# -- fusion and rendering --------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["canonical", "pixel_aligned"])
def test_fused_labels_reproduce_the_ground_truth_at_a_held_out_view(labelled_frames, method):
    inputs, target = [labelled_frames[p] for p in (0, 2, 3, 5)], labelled_frames[1]
    model = configured(method, {}).build(inputs, VOXEL, True)
    pred = render_labels(model, target)
    gt = label_map(target)
    on_covered = scores(label_confusion(gt, pred, 2, pred >= 0))
    assert (pred >= 0).float().mean() > 0.5
    assert on_covered["miou"] > 0.8 and on_covered["accuracy"] > 0.9
    assert set(pred[pred >= 0].unique().tolist()) == {0, 1}  # both surfaces drawn with their labels


def test_pixel_aligned_gaussians_carry_their_pixels_label_scores_and_merging_averages_them(labelled_frames):
    frame = labelled_frames[0]
    splats = pixel_aligned([frame], VOXEL)
    config = SceneConfig(voxel_size=VOXEL)
    valid = (frame.depth > config.range.near) & (frame.depth < config.range.far)
    assert splats.labels.shape == (int(valid.sum()), 2)
    assert torch.equal(splats.labels, frame.labels[valid])
    merged = gaussian_merge([frame], VOXEL)
    assert merged.labels.shape == (len(merged), 2)
    assert torch.allclose(merged.labels.sum(1), torch.ones(len(merged)))  # means of one-hot rows
    assert pixel_aligned([replace(frame, labels=None)], VOXEL).labels is None


# -- the probe -------------------------------------------------------------------------------------
def test_probe_separates_a_linearly_separable_set_and_is_deterministic():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(600, 5, generator=g) * torch.tensor([1.0, 10.0, 0.1, 1.0, 1.0])
    y = (x[:, 0] + 0.1 * x[:, 1] > 0).long() + 2 * (x[:, 3] > 1.0).long()  # classes 0..3 by two hyperplanes
    probe = fit_probe(x, y, 4, steps=60)
    assert (probe.predict(x) == y).float().mean() > 0.97
    again = fit_probe(x, y, 4, steps=60)
    assert torch.equal(probe.weight, again.weight) and torch.equal(probe.bias, again.bias)


@pytest.mark.parametrize("x, y, classes, field", [
    (torch.zeros(0, 3), torch.zeros(0, dtype=torch.long), 2, "features"),
    (torch.zeros(4, 3), torch.zeros(5, dtype=torch.long), 2, "labels"),
    (torch.zeros(4, 3), torch.full((4,), 2), 2, "labels"),
])
def test_fit_probe_rejects_bad_inputs_naming_the_field(x, y, classes, field):
    with pytest.raises(ValueError, match=f"^{field}:"):
        fit_probe(x, y, classes)


def client_features(frame) -> np.ndarray:  # [H, W, 8]: a fixed random projection of colour and position
    H, W = frame.height, frame.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    raw = np.concatenate([frame.rgb.numpy() / 255.0, (u / W)[..., None], (v / H)[..., None],
                          frame.depth.numpy()[..., None]], -1).astype(np.float32)
    return raw @ np.random.default_rng(7).standard_normal((6, 8)).astype(np.float32)


def test_probe_runs_on_client_features_fused_by_the_scene(labelled_frames):
    frames = [replace(f, features=client_features(f)) for f in labelled_frames]
    inputs, targets = [frames[p] for p in (0, 2, 3, 5)], [frames[1], frames[4]]
    method = parse_label_method("canonical").method({"features.backend": "client", "features.dim": 8})
    model = method.build(inputs, VOXEL, True)
    assert model.splats.features.shape[1] == 8
    all_pixels, on_covered = probe_confusion(model, inputs, targets, 2)
    assert int(all_pixels.sum()) == 2 * 48 * 64 and int(on_covered[:, 2].sum()) == 0
    assert scores(on_covered)["accuracy"] > 0.8  # box vs ground from colour, height and depth


# -- methods -----------------------------------------------------------------------------------------
def test_only_methods_that_splat_labels_and_features_run():
    assert parse_label_method("canonical:sh_degree=0").settings == {"sh_degree": 0}
    with pytest.raises(ValueError, match="^methods: open3d_tsdf cannot splat labels"):
        parse_label_method("open3d_tsdf")


# -- captures and the command line -----------------------------------------------------------------
def test_find_bins_and_a_capture_without_labels(tmp_path, apc_bins_path):
    assert [b.name for b in find_bins(apc_bins_path)] == ["bin_labels", "bin_mask"]
    assert find_bins(apc_bins_path / "bin_mask") == [apc_bins_path / "bin_mask"]
    with pytest.raises(ValueError, match="^dataset:"):
        find_bins(tmp_path)


def test_evaluate_needs_labels_on_every_frame(tmp_path, labelled_frames):
    from canonical_core.eval.segmentation import evaluate_segmentation

    for frames in ([replace(f, labels=None) for f in labelled_frames],  # a capture without labels
                   [replace(labelled_frames[0], labels=None), *labelled_frames[1:]]):  # an input without
        sequence = FrameSequence("gen", [Held(str(k), f) for k, f in enumerate(frames)])
        with pytest.raises(ValueError, match="^labels: frame '000000' of gen carries no labels"):
            evaluate_segmentation([sequence], views=[2], methods=["canonical"], out_dir=tmp_path, progress=False,
                                  voxel_size=VOXEL, probe=False)
    assert not any(tmp_path.iterdir())  # nothing written


def test_evaluate_probes_client_features_and_means_over_captures(tmp_path, labelled_frames):
    """Two captures whose every frame carries client features: each Scene method's run has the client
    probe's columns (methods that cannot fuse client features have none), and the report's mean over
    the captures is their per-metric mean (None where a capture lacks the metric)."""
    from canonical_core.eval.segmentation import evaluate_segmentation

    frames = [replace(f, features=client_features(f)) for f in labelled_frames]
    sequences = [FrameSequence(name, [Held(str(k), f) for k, f in enumerate(order)])
                 for name, order in (("one", frames), ("two", frames[::-1]))]  # other inputs, other scores
    results = evaluate_segmentation(sequences, views=[2], methods=["canonical", "pixel_aligned"], out_dir=tmp_path,
                                    progress=False, voxel_size=VOXEL)
    runs = {(b["dataset"], r["method"]): r for b in results["bins"] for r in b["runs"]}
    canonical, aligned = runs[("one", "canonical")], runs[("one", "pixel_aligned")]
    assert all(b["client_features"] for b in results["bins"])
    assert 0.8 < canonical["client_probe_accuracy_covered"] <= 1  # box vs ground from colour, height and depth
    assert not any(k.startswith("client_probe") for k in aligned)
    mean, other = {r["method"]: r for r in results["mean"]}, runs[("two", "canonical")]
    for key in ("fusion_miou", "probe_miou", "client_probe_miou", "coverage"):
        assert mean["canonical"][key] == pytest.approx((canonical[key] + other[key]) / 2), key
    assert canonical["probe_miou"] != other["probe_miou"]  # the two captures score apart: a real mean
    assert mean["pixel_aligned"]["client_probe_miou"] is None and mean["pixel_aligned"]["probe_miou"] is not None


@dataclass(frozen=True)
class Held:
    """A frame source that holds its frame."""

    frame_id: str
    frame: object

    def load(self):
        return self.frame


def small_bin(source: Path, dest: Path, count: int = 6) -> Path:
    """The first ``count`` frames of a label-fusion bin, copied as they are."""
    dest.mkdir(parents=True)
    shutil.copy(source / "camera-intrinsics.color.txt", dest)
    for k in range(count):
        for f in source.glob(f"frame-{k:06d}.*"):
            shutil.copy(f, dest)
    return dest


def test_cli_segmentation_runs_end_to_end_on_a_small_real_bin(tmp_path, apc_bins_path, capsys):
    data = small_bin(apc_bins_path / "bin_labels", tmp_path / "bin_labels")
    out = tmp_path / "out"
    out.mkdir()
    (out / "grid_bin_labels_N8.png").write_bytes(b"")  # an earlier run's grid: not this run's, so removed
    assert main([str(data), "--segmentation", "--views", "2", "--methods", "canonical", "--scale", "0.25",
                 "--out", str(out)]) == 0
    assert sorted(p.name for p in out.glob("grid_*.png")) == ["grid_bin_labels_N2.png"]
    printed = capsys.readouterr().out
    assert "| bin_labels | canonical | 2 |" in printed
    results = json.loads((out / "results.json").read_text())
    (run,) = results["bins"][0]["runs"]
    assert results["bins"][0]["label_ids"] == [0, 48, 132] and results["bins"][0]["heldout"] == [1, 4]
    assert 0 < run["fusion_miou"] <= run["fusion_miou_covered"] <= 1 and 0 < run["probe_accuracy"] <= 1
    grid = Image.open(out / "grid_bin_labels_N2.png")
    assert grid.width == 3 * 160  # image, ground truth, canonical
    assert (out / "miou_vs_views.png").is_file() and "| capture | method | N |" in (out / "results.md").read_text()
    assert main([str(data), "--segmentation", "--views", "9", "--out", str(out), "--quiet"]) == 2
    assert "views" in capsys.readouterr().err


def test_a_split_that_does_not_fit_says_how_many_frames_are_held_out():
    with pytest.raises(ValueError, match=r"^views: 5 input views requested, but 6 frames with one in every 3 held out "
                                         r"leave 4 inputs and 2 held out$"):
        segmentation_split(6, [5], 3)


def test_a_segmentation_run_removes_the_evaluations_figures_from_its_folder(tmp_path, labelled_frames):
    from canonical_core.eval.segmentation import evaluate_segmentation

    stale = ("psnr_vs_views.png", "noise_psnr.png", "stability.png", "grid_N2.png")
    for name in (*stale, "notes.png"):
        (tmp_path / name).write_bytes(b"")
    sequence = FrameSequence("gen", [Held(str(k), f) for k, f in enumerate(labelled_frames)])
    evaluate_segmentation([sequence], views=[2], methods=["canonical"], out_dir=tmp_path, progress=False,
                          voxel_size=VOXEL, probe=False)
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["grid_gen_N2.png", "miou_vs_views.png", "notes.png"]
