"""End to end on tiny configurations: files written, JSON shape, held-out frames never inputs."""

from __future__ import annotations

import json
import math

import pytest
import torch
from PIL import Image

from canonical_core.datasets import load_dataset, synthetic_rgbd
from canonical_core.eval import evaluate
from canonical_core.eval.open3d_tsdf import open3d_available
from canonical_core.eval.run import add_depth_noise, default_voxel_size

RUN_KEYS = {"method", "views", "noise", "psnr", "psnr_covered", "coverage", "psnr_ceiling", "ssim", "gaussians", "fold_ms", "render_ms",
            "depth_agreement"}


def _check_results(results: dict, out_dir, methods, views, noise) -> None:
    on_disk = json.loads((out_dir / "results.json").read_text())
    assert on_disk["dataset"] == results["dataset"]
    assert {"dataset", "heldout", "runs", "stability"} <= set(on_disk)
    heldout = set(on_disk["heldout"])
    assert len(heldout) == 10
    for n in views:
        assert not heldout & set(on_disk["inputs"][str(n)])
    if on_disk["extrapolation"] is not None:
        for inputs in on_disk["extrapolation"]["inputs"].values():
            assert not heldout & set(inputs)
    for inputs in on_disk["stability_inputs"].values():
        assert not heldout & set(inputs)
    runs = on_disk["runs"]
    assert {(r["method"], r["views"], r["noise"]) for r in runs} == {
        (m, n, lv) for m in methods for n in views for lv in [0.0, *noise]}
    for r in runs:
        assert set(r) == RUN_KEYS
        assert math.isfinite(r["psnr"]) and 0 <= r["coverage"] <= 1 and -1 <= r["ssim"] <= 1
        assert r["psnr_ceiling"] is None or r["psnr_ceiling"] > 0
        assert r["depth_agreement"] is None or 0 <= r["depth_agreement"] <= 1
        assert r["fold_ms"] > 0 and r["render_ms"] > 0
        assert r["gaussians"] is None if r["method"] == "open3d_tsdf" else r["gaussians"] > 0
    for s in on_disk["stability"]:
        assert set(s) == {"method", "views", "cosine"} and -1 <= s["cosine"] <= 1 + 1e-9
    md = (out_dir / "results.md").read_text()
    assert "Held-out positions" in md and all(f"| {m} |" in md for m in methods)
    pngs = sorted(p.name for p in out_dir.glob("*.png"))
    expected = {"psnr_vs_views.png", *(f"grid_N{n}.png" for n in views)}
    expected |= {"noise_psnr.png"} if noise else set()
    expected |= {"stability.png"} if on_disk["stability"] else set()
    assert set(pngs) == expected
    for name in pngs:
        with Image.open(out_dir / name) as img:
            img.load()
            assert img.width > 50 and img.height > 50


def test_synthetic_sample_end_to_end(tmp_path):
    methods = ["canonical", "pixel_aligned"] + (["open3d_tsdf"] if open3d_available() else [])
    seq = synthetic_rgbd(num_frames=22, width=48, height=36)
    results = evaluate(seq, views=[2, 4], methods=methods, noise=[0.1], out_dir=tmp_path, progress=False,
                       voxel_size=0.04, stability_views=[2, 3])
    _check_results(results, tmp_path, methods, [2, 4], [0.1])
    assert results["extrapolation"] is not None
    assert {r["method"] for r in results["stability"]} == {"canonical", "pixel_aligned"}
    assert [r["cosine"] for r in results["stability"] if r["views"] == 3] == pytest.approx([1.0, 1.0])
    # the grid holds ground truth plus one column per method, three held-out frames
    with Image.open(tmp_path / "grid_N4.png") as grid:
        assert grid.width == 48 * (1 + len(methods))


def test_downscaled_shelf_slice_end_to_end(tmp_path, shelf_dir):
    seq = load_dataset(shelf_dir, max_frames=16)
    results = evaluate(seq, views=[2, 4], methods=["canonical", "gaussian_merge"], out_dir=tmp_path, progress=False,
                       scale=0.125, stability_views=[], extrapolation=False)
    _check_results(results, tmp_path, ["canonical", "gaussian_merge"], [2, 4], [])
    assert results["image_size"] == [80, 60]
    assert results["voxel_size"] == pytest.approx(6 * 0.41 / (615.195 / 8), rel=0.15)  # 6 footprints at ~0.41 m
    assert results["heldout"] == [2, 3, 4, 6, 7, 8, 9, 11, 12, 13] and results["stability"] == []


def test_noise_is_seeded_and_scaled_by_the_median_depth():
    frame = synthetic_rgbd(num_frames=1, width=64, height=48)[0]
    a, b = add_depth_noise(frame, 0.1, 3), add_depth_noise(frame, 0.1, 3)
    assert torch.equal(a.depth, b.depth)
    assert not torch.equal(a.depth, add_depth_noise(frame, 0.1, 4).depth)
    assert add_depth_noise(frame, 0.0, 3) is frame
    valid = frame.depth > 0
    assert torch.equal(a.depth[~valid], frame.depth[~valid])  # missing stays missing
    both = valid & (a.depth > 0)
    ratio = float((a.depth - frame.depth)[both].std()) / float(frame.depth[valid].median())
    assert ratio == pytest.approx(0.1, rel=0.1)
    with pytest.raises(ValueError, match="noise"):
        add_depth_noise(frame, -0.1, 0)


def test_default_voxel_size_is_positive():
    assert default_voxel_size(synthetic_rgbd(num_frames=1, width=64, height=48)) > 0


def test_evaluate_refuses_bad_arguments(tmp_path):
    seq = synthetic_rgbd(num_frames=22, width=48, height=36)
    with pytest.raises(ValueError, match="methods"):
        evaluate(seq, views=[2], methods=["bogus"], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="noise"):
        evaluate(seq, views=[2], methods=["canonical"], noise=[-1.0], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="views"):
        evaluate(seq, views=[16], methods=["canonical"], out_dir=tmp_path, progress=False)
    assert not (tmp_path / "results.json").exists()
