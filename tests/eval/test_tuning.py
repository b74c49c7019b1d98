"""Defaults chosen across captures: the objective and the per-group changes against hand values, a
capture scored for real, and the recorded tuning rounds decided again by today's rule (the defaults
in the code are what the recorded numbers choose)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from canonical_core.eval.tuning import (DEFAULT, Capture, Variant, agreement, default_of, group_changes, main, objective,
                                        score_capture)

RECORDED = Path(__file__).resolve().parents[2] / "docs" / "eval"


def per_n(psnr: float, covered: float, agree: float) -> dict:
    return {2: {"psnr": psnr, "psnr_covered": covered, "depth_agreement": agree},
            4: {"psnr": psnr + 2, "psnr_covered": covered + 2, "depth_agreement": agree + 0.2}}


def test_objective_agreement_and_group_changes_by_hand():
    assert objective(per_n(10, 14, 0.5)) == pytest.approx(13.0)  # ((10 + 14) / 2 + (12 + 16) / 2) / 2
    assert agreement(per_n(10, 14, 0.5)) == pytest.approx(0.6)
    captures = [  # two captures of group a, one of group b; x gains 1 dB all-pixel on the first, 2 covered on the second
        {"group": "a", "variants": {"default": per_n(10, 14, 0.5), "x": per_n(11, 14, 0.5)}},
        {"group": "a", "variants": {"default": per_n(8, 12, 0.5), "x": per_n(8, 14, 0.4)}},
        {"group": "b", "variants": {"default": per_n(9, 13, 0.5), "x": per_n(9, 12, 0.5)}},
    ]
    changes = group_changes(captures)
    assert changes["a"] == pytest.approx({"default": 0.0, "x": (0.5 + 1.0) / 2})
    assert changes["b"] == pytest.approx({"default": 0.0, "x": -0.5})
    assert group_changes(captures, agreement)["a"]["x"] == pytest.approx(-0.05)


def test_score_capture_runs_the_protocol_for_every_variant(apc_bins_path):
    variants = [DEFAULT, Variant("sh_degree=0", {"sh_degree": 0})]
    result = score_capture(Capture(str(apc_bins_path / "bin_labels"), "apc_bins"), variants, scale=0.25)
    assert result["group"] == "apc_bins" and result["views"] == [2, 4] and result["voxel_size"] > 0
    assert set(result["variants"]) == {"default", "sh_degree=0"}
    for rows in result["variants"].values():
        assert set(rows) == {2, 4}
        for m in rows.values():
            assert all(math.isfinite(m[k]) for k in ("psnr", "psnr_covered", "coverage", "depth_agreement", "ssim"))
            assert 0 < m["coverage"] <= 1 and 5 < m["psnr"] < 40
    assert result["variants"]["default"][4]["psnr"] != result["variants"]["sh_degree=0"][4]["psnr"]


@pytest.mark.parametrize("recorded, decisions", [
    ("tuning_rounds/b", {"free_space.margin": "free_space.margin=0", "decoder.opacity_slope": "decoder.opacity_slope=3"}),
    # today's defaults against the old values put back: neither is chosen back
    ("tuning", {"free_space.margin": "default kept", "decoder.opacity_slope": "default kept"}),
])
def test_the_recorded_rounds_decide_the_defaults_in_the_code(tmp_path, capsys, recorded, decisions):
    assert main(["--out", str(tmp_path), "--decide-from", str(RECORDED / recorded / "results.json")]) == 0
    report = (tmp_path / "results.md").read_text()
    for knob, decision in decisions.items():
        assert f"| {knob} | {decision} |" in report
    assert (default_of("free_space.margin"), default_of("decoder.opacity_slope")) == (0.0, 3.0)
    assert json.loads((tmp_path / "results.json").read_text())["decided_by"].endswith(f"{recorded}/results.json")
    assert (tmp_path / "objectives.png").stat().st_size > 0 and "Leave-one-capture-out" in capsys.readouterr().out


@pytest.mark.parametrize("args, flag", [
    (["--variants", "foo"], "--variants"),
    (["--scale", "0"], "--scale"),
    (["--scale", "1.5"], "--scale"),
    (["--views", "2,x"], "--views"),
    (["--views", "0"], "--views"),
    (["--decide-from", "/nonexistent.json"], "--decide-from"),
    (["--out", "/proc/no/such/folder"], "--out"),  # found only once every run had ended, before
])
def test_bad_arguments_exit_2_naming_the_flag_before_any_run(tmp_path, capsys, monkeypatch, args, flag):
    monkeypatch.setattr("canonical_core.eval.tuning.load_dataset", lambda *a, **k: pytest.fail("a capture was loaded"))
    with pytest.raises(SystemExit) as exit_:
        main(["--out", str(tmp_path / "out"), *args])
    assert exit_.value.code == 2
    assert f"error: {flag}: " in capsys.readouterr().err


def test_decide_from_a_file_that_is_not_tuning_results_exits_2(tmp_path, capsys):
    for text in ("{not json", json.dumps({"captures": "x"}), json.dumps({"captures": []}),
                 json.dumps({"captures": [{"x": 1}]}), json.dumps({"captures": [{"group": "g", "variants": {"other": {}}}]})):
        saved = tmp_path / "results.json"
        saved.write_text(text)
        with pytest.raises(SystemExit) as exit_:
            main(["--out", str(tmp_path / "out"), "--decide-from", str(saved)])
        assert exit_.value.code == 2 and "error: --decide-from: " in capsys.readouterr().err, text


def test_views_no_capture_allows_exit_2_naming_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--out", str(tmp_path / "out"), "--views", "100", "--variants", "default"])
    assert exit_.value.code == 2 and "error: --views: " in capsys.readouterr().err
