"""``python -m canonical_core.eval`` and the library entry points on a bad --out, Ctrl-C, the
segmentation experiment's 'do nothing' options, and the figures of the other experiment left in
a shared output folder."""

from __future__ import annotations

import os

import pytest

from canonical_core.datasets import synthetic_rgbd, write_tsdf_fusion
from canonical_core.eval.cli import main

TINY = ["--views", "2", "--methods", "canonical", "--voxel-size", "0.05", "--stability-views", "none",
        "--no-extrapolation", "--quiet"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_tsdf_fusion(synthetic_rgbd(num_frames=14, width=40, height=30), tmp_path_factory.mktemp("cap"))


def bad_outs(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    yield blocker  # an existing file
    yield blocker / "sub"  # a folder under a file
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        yield locked


@pytest.fixture()
def labelled(apc_bins_path):
    return apc_bins_path / "bin_labels"


@pytest.mark.parametrize("segmentation", [False, True])
def test_a_bad_out_is_refused_before_anything_runs(tmp_path, capture, labelled, capsys, monkeypatch, segmentation):
    def never(*args, **kwargs):
        raise AssertionError("a method ran before --out was checked")

    monkeypatch.setattr("canonical_core.eval.run.build", never)
    monkeypatch.setattr("canonical_core.eval.segmentation.run_bin", never)
    for out in bad_outs(tmp_path):
        extra = ["--segmentation", "--views", "2", "--methods", "canonical", "--quiet"] if segmentation else TINY
        assert main([str(labelled if segmentation else capture), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"canonical eval: error: --out: cannot write {out}: "), err
        assert err.count("\n") == 1


def test_the_library_entry_points_name_out_dir(tmp_path, capture, labelled):
    from canonical_core.eval.run import evaluate
    from canonical_core.eval.segmentation import evaluate_segmentation

    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ValueError, match="^out_dir: cannot write"):
        evaluate(capture, views=[2], methods=["canonical"], out_dir=blocker / "x", progress=False)
    with pytest.raises(ValueError, match="^out_dir: cannot write"):
        evaluate_segmentation(labelled, views=[2], methods=["canonical"], out_dir=blocker, progress=False)


def test_ctrl_c_says_interrupted_and_exits_130(tmp_path, capture, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("canonical_core.eval.run.evaluate", interrupted)
    assert main([str(capture), "--out", str(tmp_path / "out"), *TINY]) == 130
    assert capsys.readouterr().err == "interrupted\n"


def test_segmentation_takes_the_options_that_mean_do_nothing(tmp_path, capture, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr("canonical_core.eval.segmentation.evaluate_segmentation", lambda *a, **k: calls.append(k))
    assert main([str(capture), "--segmentation", "--out", str(tmp_path), "--stability-views", "none",
                 "--no-extrapolation", "--quiet"]) == 0
    assert len(calls) == 1
    assert main([str(capture), "--segmentation", "--out", str(tmp_path), "--stability-views", "2,4", "--quiet"]) == 2
    assert "--stability-views: not used by --segmentation" in capsys.readouterr().err


def test_an_evaluation_removes_the_segmentation_experiments_figures_from_its_folder(tmp_path, capture):
    out = tmp_path / "out"
    out.mkdir()
    for name in ("miou_vs_views.png", "grid_bin_labels_N2.png", "notes.png"):
        (out / name).write_bytes(b"")
    assert main([str(capture), "--out", str(out), *TINY]) == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["grid_N2.png", "notes.png", "psnr_vs_views.png"]


def test_ctrl_c_writes_the_runs_finished_so_far_marked_partial(tmp_path, capture, capsys, monkeypatch):
    import json

    from canonical_core.eval import run

    groups = []

    def interrupt_the_second_group(*args):
        groups.append(1)
        if len(groups) == 2:
            raise KeyboardInterrupt
        return common(*args)

    common = run.add_common_psnr
    monkeypatch.setattr(run, "add_common_psnr", interrupt_the_second_group)
    out = tmp_path / "out"
    out.mkdir()
    (out / "psnr_vs_views.png").write_bytes(b"")  # an earlier run's figure: not of these results
    assert main([str(capture), "--out", str(out), *TINY, "--views", "2,4"]) == 130
    assert capsys.readouterr().err.endswith("interrupted\n")
    results = json.loads((out / "results.json").read_text())
    assert results["partial"] is True and [(r["method"], r["views"]) for r in results["runs"]] == [("canonical", 2)]
    text = (out / "results.md").read_text()
    assert "partial" in text.lower() and "| canonical | 2 |" in text and "| canonical | 4 |" not in text
    assert not list(out.glob("*.png"))


def test_ctrl_c_in_the_segmentation_experiment_writes_the_runs_finished_so_far(tmp_path, labelled, capsys, monkeypatch):
    import json

    from canonical_core.eval import segmentation

    fusion_rows = []

    def interrupt_the_second_run(kind, *args):
        if kind == "fusion":
            fusion_rows.append(1)
            if len(fusion_rows) == 2:
                raise KeyboardInterrupt
        return row(kind, *args)

    row = segmentation._row
    monkeypatch.setattr(segmentation, "_row", interrupt_the_second_run)
    out = tmp_path / "out"
    out.mkdir()
    (out / "miou_vs_views.png").write_bytes(b"")  # an earlier run's figure: not of these results
    assert main([str(labelled), "--segmentation", "--views", "2,4", "--methods", "canonical", "--scale", "0.25",
                 "--out", str(out), "--quiet"]) == 130
    assert capsys.readouterr().err.endswith("interrupted\n")
    results = json.loads((out / "results.json").read_text())
    assert results["partial"] is True and results["mean"] == []
    assert [(b["dataset"], r["method"], r["views"]) for b in results["bins"] for r in b["runs"]] == [("bin_labels", "canonical", 2)]
    text = (out / "results.md").read_text()
    assert "partial" in text.lower() and "| bin_labels | canonical | 2 |" in text and "| 4 |" not in text
    assert not list(out.glob("*.png"))
