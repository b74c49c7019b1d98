"""The ``eval`` subcommand: argument parsing, hooking into a parent parser, a tiny run."""

from __future__ import annotations

import argparse
import json

from canonical_core.datasets import synthetic_rgbd, write_tsdf_fusion
from canonical_core.eval.cli import add_eval_parser, main, run_eval


def test_add_eval_parser_hooks_into_a_parent_parser(tmp_path):
    parser = argparse.ArgumentParser(prog="canonical")
    add_eval_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "data/x", "--views", "2,4,8,16", "--out", str(tmp_path),
                              "--methods", "canonical,open3d_tsdf", "--noise", "0.05,0.1,0.25,0.5"])
    assert args.func is run_eval
    assert args.views == [2, 4, 8, 16] and args.methods == ["canonical", "open3d_tsdf"]
    assert args.noise == [0.05, 0.1, 0.25, 0.5] and args.scale == 1.0 and args.stability_views is None
    assert args.mixed_noise is None
    assert parser.parse_args(["eval", "x", "--out", "o", "--stability-views", "none"]).stability_views == []
    assert parser.parse_args(["eval", "x", "--out", "o", "--mixed-noise", "0.25"]).mixed_noise == 0.25
    assert args.colour == "normalised" and args.depth_scale is None
    assert parser.parse_args(["eval", "x", "--out", "o", "--depth-scale", "1000"]).depth_scale == 1000.0
    assert parser.parse_args(["eval", "x", "--out", "o", "--colour", "composited"]).colour == "composited"


def test_cli_runs_a_tiny_evaluation_and_reports_errors(tmp_path, capsys):
    data = write_tsdf_fusion(synthetic_rgbd(num_frames=14, width=40, height=30), tmp_path / "cap")
    out = tmp_path / "out"
    out.mkdir()
    for name in ("grid_N16.png", "stability.png", "notes.png"):  # an earlier run's figures, and a user's file
        (out / name).write_bytes(b"")
    assert main([str(data), "--views", "2", "--out", str(out), "--methods", "canonical", "--voxel-size", "0.05",
                 "--stability-views", "none", "--no-extrapolation"]) == 0
    assert "## Held-out views, clean depth" in capsys.readouterr().out
    assert sorted(p.name for p in out.glob("*.png")) == ["grid_N2.png", "notes.png", "psnr_vs_views.png"]
    assert json.loads((out / "results.json").read_text())["runs"][0]["method"] == "canonical"
    assert main([str(data), "--views", "2", "--out", str(out), "--methods", "nerf", "--quiet"]) == 2
    assert "methods" in capsys.readouterr().err
    assert main([str(data), "--views", "2", "--out", str(out), "--mixed-noise", "-1", "--quiet"]) == 2
    assert "mixed_noise" in capsys.readouterr().err
    # counts the capture has no frames for are refused, where they were left out silently
    assert main([str(data), "--views", "2", "--out", str(out), "--methods", "canonical", "--stability-views", "2,9",
                 "--quiet"]) == 2
    assert "stability_views: [9] do not fit" in capsys.readouterr().err
    # the segmentation experiment would ignore them: said, and nothing runs
    assert main([str(data), "--segmentation", "--out", str(tmp_path / "seg"), "--noise", "0.1", "--no-extrapolation",
                 "--quiet"]) == 2
    assert capsys.readouterr().err.startswith("canonical eval: error: --noise: not used by "
                                              "--segmentation") and not (tmp_path / "seg").exists()


def test_a_capture_without_intrinsics_is_evaluated_with_K(tmp_path, capsys):
    frames = synthetic_rgbd(num_frames=14, width=40, height=30)
    data = write_tsdf_fusion(frames, tmp_path / "cap")
    for intrinsics in data.glob("*intrinsics*"):
        intrinsics.unlink()
    common = ["--views", "2", "--methods", "canonical", "--voxel-size", "0.05", "--stability-views", "none",
              "--no-extrapolation", "--quiet"]
    assert main([str(data), "--out", str(tmp_path / "a"), *common]) == 2
    assert "no intrinsics file" in capsys.readouterr().err and not (tmp_path / "a").exists()
    K = frames[0].camera.K64()
    assert main([str(data), "--out", str(tmp_path / "b"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", *common]) == 0
    assert json.loads((tmp_path / "b" / "results.json").read_text())["runs"][0]["method"] == "canonical"
