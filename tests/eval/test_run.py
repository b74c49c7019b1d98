"""End to end on tiny configurations: files written, JSON shape, held-out frames never inputs."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest
import torch
from PIL import Image

from canonical_core.datasets import load_dataset, synthetic_rgbd
from canonical_core.eval import evaluate
from canonical_core.eval.open3d_tsdf import open3d_available
from canonical_core.eval.methods import build
from canonical_core.eval.run import Scored, add_common_psnr, add_fixed_psnr, add_depth_noise, add_mixed_depth_noise, default_voxel_size, score
from canonical_core.frame import resize_frame

RUN_KEYS = {"method", "views", "noise", "psnr", "psnr_covered", "coverage", "psnr_ceiling", "ssim", "gaussians", "fold_ms", "render_ms",
            "depth_agreement", "psnr_common", "common_coverage", "psnr_fixed", "psnr_edge", "psnr_flat", "edge_share"}


def _check_group_common(runs: list[dict]) -> None:
    """Runs on the same inputs share one common-pixel share, no larger than any method's coverage."""
    share = runs[0]["common_coverage"]
    assert all(r["common_coverage"] == share for r in runs)
    assert 0 <= share <= min(r["coverage"] for r in runs) + 1e-12
    for r in runs:
        assert (r["psnr_common"] is None) == (share == 0)


def _check_results(results: dict, out_dir, methods, views, noise, mixed=None) -> None:
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
    mixed_runs = [] if mixed is None else on_disk["mixed_noise"]["runs"]
    assert (on_disk["mixed_noise"] is None) == (mixed is None)
    assert {(r["method"], r["views"], r["noise"]) for r in mixed_runs} == (
        set() if mixed is None else {(m, n, mixed) for m in methods for n in views})
    extra_runs = [] if on_disk["extrapolation"] is None else on_disk["extrapolation"]["runs"]
    for group_runs in (runs, mixed_runs, extra_runs):
        for key in {(r["views"], r["noise"]) for r in group_runs}:
            _check_group_common([r for r in group_runs if (r["views"], r["noise"]) == key])
    for r in runs + mixed_runs + extra_runs:
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
    assert "pixels every method covers" in md and ("Mixed-quality inputs" in md) == (mixed is not None)
    assert "pixels the smallest N covers" in md
    # at the smallest N of each condition the fixed pixels are the run's own covered ones
    for group_runs in (runs, mixed_runs, extra_runs):
        for r in group_runs:
            first = min(x["views"] for x in group_runs if x["noise"] == r["noise"])
            if r["views"] == first and r["psnr_covered"] is not None:
                assert r["psnr_fixed"] == pytest.approx(r["psnr_covered"], abs=0.05)
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
    results = evaluate(seq, views=[2, 4], methods=methods, noise=[0.1], mixed_noise=0.2, out_dir=tmp_path,
                       progress=False, voxel_size=0.04, stability_views=[2, 3])
    _check_results(results, tmp_path, methods, [2, 4], [0.1], mixed=0.2)
    assert results["extrapolation"] is not None
    assert {r["method"] for r in results["stability"]} == {"canonical", "pixel_aligned"}
    assert [r["cosine"] for r in results["stability"] if r["views"] == 3] == pytest.approx([1.0, 1.0])
    # the grid holds ground truth plus one column per method, three held-out frames
    with Image.open(tmp_path / "grid_N4.png") as grid:
        assert grid.width == 48 * (1 + len(methods))
    # results.md reads canonical's lead over each other method off the runs: its value minus theirs
    report = (tmp_path / "results.md").read_text()
    clean = {(r["method"], r["views"]): r for r in results["runs"] if r["noise"] == 0}
    lead = clean["canonical", 4]["psnr_common"] - clean["pixel_aligned", 4]["psnr_common"]
    assert "## canonical against the other methods, clean depth" in report
    assert f"| pixel_aligned | 4 | {lead:+.2f} |" in report
    assert "## More views: the worst step from one N to the next, clean depth" in report


def test_a_method_with_settings_runs_under_its_label(tmp_path):
    seq = synthetic_rgbd(num_frames=22, width=48, height=36)
    methods = ["canonical", "canonical:sh_degree=0"]
    results = evaluate(seq, views=[2], methods=methods, out_dir=tmp_path, progress=False, voxel_size=0.04,
                       stability_views=[], extrapolation=False)
    assert results["methods"] == methods
    runs = {r["method"]: r for r in results["runs"]}
    assert set(runs) == set(methods) and runs["canonical"]["gaussians"] == runs["canonical:sh_degree=0"]["gaussians"]
    assert "canonical:sh_degree=0" in (tmp_path / "results.md").read_text()


@pytest.mark.realdata
def test_downscaled_shelf_slice_end_to_end(tmp_path, shelf_dir):
    seq = load_dataset(shelf_dir, max_frames=16)
    results = evaluate(seq, views=[2, 4], methods=["canonical", "gaussian_merge"], out_dir=tmp_path, progress=False,
                       scale=0.125, stability_views=[], extrapolation=False)
    _check_results(results, tmp_path, ["canonical", "gaussian_merge"], [2, 4], [])
    assert results["image_size"] == [80, 60]
    assert results["voxel_size"] == pytest.approx(6 * 0.41 / (615.195 / 8), rel=0.15)  # 6 footprints at ~0.41 m
    assert results["heldout"] == [2, 3, 4, 6, 7, 8, 9, 11, 12, 13] and results["stability"] == []
    assert results["colour"] == "normalised" and "normalised colour" in (tmp_path / "results.md").read_text()


@pytest.mark.realdata
def test_scores_in_either_colour_mode_differ_only_where_pixels_are_partly_covered(shelf_frames):
    # normalised colour is the composited image over black divided by alpha: the two agree where a
    # pixel is fully covered or empty, and the normalised one is brighter where it is partly covered
    inputs, target = [shelf_frames[0], shelf_frames[6]], shelf_frames[3]
    model = build("canonical", [resize_frame(f, 0.25) for f in inputs], 0.008)[0]
    small = resize_frame(target, 0.25)
    composited = model.render(small.camera, colour="composited")
    normalised = model.render(small.camera)  # the protocol's default
    assert torch.equal(composited.alpha, normalised.alpha) and torch.equal(composited.depth, normalised.depth)
    partly = (composited.alpha > 0.05) & (composited.alpha < 0.95)
    assert 0.01 < partly.float().mean() < 0.9
    expected = (composited.rgb / composited.alpha.clamp_min(1e-12)[..., None]).clamp(0, 1)
    assert torch.allclose(normalised.rgb[partly], expected[partly], atol=2e-3)
    full_or_empty = (composited.alpha > 0.9999) | (composited.alpha == 0)
    assert torch.allclose(normalised.rgb[full_or_empty], composited.rgb[full_or_empty], atol=2e-3)
    scores = {mode: score(model, [small], 0.008, mode).metrics for mode in ("composited", "normalised")}
    assert scores["normalised"]["coverage"] == scores["composited"]["coverage"]
    assert scores["normalised"]["psnr"] != scores["composited"]["psnr"]


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


def test_mixed_noise_reaches_every_other_input_only():
    seq = synthetic_rgbd(num_frames=5, width=32, height=24)
    frames = [seq[k] for k in range(5)]
    positions = [0, 3, 5, 8, 9]
    mixed = add_mixed_depth_noise(frames, positions, 0.2)
    for k, (before, after, p) in enumerate(zip(frames, mixed, positions)):
        if k % 2:
            assert torch.equal(after.depth, add_depth_noise(before, 0.2, p).depth)
        else:
            assert after is before
    with pytest.raises(ValueError, match="positions"):
        add_mixed_depth_noise([frames[0]], [0, 1], 0.2)


def test_common_psnr_is_the_psnr_on_the_pixels_every_run_covers():
    torch.manual_seed(0)
    target = synthetic_rgbd(num_frames=1, width=8, height=8)[0]
    gt = target.rgb.float() / 255.0
    images = [torch.randint(0, 256, (8, 8, 3), dtype=torch.uint8) for _ in range(2)]
    masks = [torch.zeros(8, 8, dtype=torch.bool) for _ in range(2)]
    masks[0][:4] = True  # rows 0-3
    masks[1][2:] = True  # rows 2-7: both cover rows 2-3
    scored = [Scored({}, [img.numpy()], [m]) for img, m in zip(images, masks)]
    runs = [{}, {}]
    add_common_psnr(runs, scored, [target])
    for run, img in zip(runs, images):
        err = (img[2:4].double() / 255.0 - gt[2:4].double()) ** 2
        assert run["psnr_common"] == pytest.approx(-10 * math.log10(float(err.mean())), abs=1e-5)  # float32 / 255
        assert run["common_coverage"] == pytest.approx(16 / 64)
    masks[1][:] = False  # no pixel in common: no number, not a zero
    runs = [{}, {}]
    add_common_psnr(runs, [Scored({}, [img.numpy()], [m]) for img, m in zip(images, masks)], [target])
    assert runs[0]["psnr_common"] is None and runs[0]["common_coverage"] == 0


def test_common_psnr_splits_into_pixels_near_a_depth_edge_and_the_rest():
    # the held-out depth steps from 1 m to 2 m between columns 15 and 16: columns 12-19 are the
    # edge; one render is exact away from it and off by 0.2 on it, the other off by 0.1 everywhere
    target = synthetic_rgbd(num_frames=1, width=32, height=24)[0]
    depth = torch.ones(24, 32)
    depth[:, 16:] = 2.0
    target = replace(target, rgb=torch.full((24, 32, 3), 100, dtype=torch.uint8), depth=depth)
    gt = target.rgb.float() / 255.0
    speckled = gt.clone()
    speckled[:, 12:20] += 0.2
    offset = gt + 0.1
    images = [(img * 255.0).round().clamp(0, 255).to(torch.uint8).numpy() for img in (speckled, offset)]
    everything = torch.ones(24, 32, dtype=torch.bool)
    runs = [{}, {}]
    add_common_psnr(runs, [Scored({}, [img], [everything]) for img in images], [target])

    def expected(image, columns):
        err = (torch.from_numpy(image)[:, columns].double() / 255.0 - gt[:, columns].double()) ** 2
        return -10 * math.log10(float(err.mean()))

    edge, flat = list(range(12, 20)), [*range(12), *range(20, 32)]
    assert runs[0]["psnr_flat"] == math.inf and runs[0]["psnr_edge"] == pytest.approx(expected(images[0], edge), abs=1e-5)
    assert runs[1]["psnr_edge"] == pytest.approx(expected(images[1], edge), abs=1e-5)
    assert runs[1]["psnr_flat"] == pytest.approx(expected(images[1], flat), abs=1e-5)
    assert runs[0]["edge_share"] == runs[1]["edge_share"] == pytest.approx(8 / 32)
    # a held-out frame without depth has no split
    runs = [{}]
    add_common_psnr(runs, [Scored({}, [images[0]], [everything])], [replace(target, depth=None)])
    assert runs[0]["psnr_edge"] is None and runs[0]["psnr_flat"] is None and runs[0]["edge_share"] is None


def test_fixed_psnr_is_the_psnr_on_the_pixels_the_smallest_n_covered_and_still_covers():
    torch.manual_seed(1)
    target = synthetic_rgbd(num_frames=1, width=8, height=8)[0]
    gt = target.rgb.float() / 255.0
    image = torch.randint(0, 256, (8, 8, 3), dtype=torch.uint8)
    first, now = torch.zeros(8, 8, dtype=torch.bool), torch.zeros(8, 8, dtype=torch.bool)
    first[:, :3] = True  # columns 0-2 at the smallest N
    now[:, 1:] = True  # columns 1-7 now: columns 1-2 are the fixed pixels
    run = {}
    add_fixed_psnr(run, Scored({}, [image.numpy()], [now]), [first], [gt])
    err = (image[:, 1:3].double() / 255.0 - gt[:, 1:3].double()) ** 2
    assert run["psnr_fixed"] == pytest.approx(-10 * math.log10(float(err.mean())), abs=1e-5)
    add_fixed_psnr(run, Scored({}, [image.numpy()], [~first]), [first], [gt])
    assert run["psnr_fixed"] is None  # none of the first pixels is still covered: no number


def test_default_voxel_size_is_positive():
    assert default_voxel_size(synthetic_rgbd(num_frames=1, width=64, height=48)) > 0


def test_evaluate_refuses_bad_arguments(tmp_path):
    seq = synthetic_rgbd(num_frames=22, width=48, height=36)
    with pytest.raises(ValueError, match="methods"):
        evaluate(seq, views=[2], methods=["bogus"], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="noise"):
        evaluate(seq, views=[2], methods=["canonical"], noise=[-1.0], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="mixed_noise"):
        evaluate(seq, views=[2], methods=["canonical"], mixed_noise=0.0, out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="views"):
        evaluate(seq, views=[16], methods=["canonical"], out_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="colour"):
        evaluate(seq, views=[2], methods=["canonical"], colour="premultiplied", out_dir=tmp_path, progress=False)
    assert not (tmp_path / "results.json").exists()
