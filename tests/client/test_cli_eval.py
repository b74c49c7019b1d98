"""``canonical eval``: the offline evaluation through the ``canonical`` command, as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from canonical_core.datasets import synthetic_rgbd, write_tsdf_fusion

REPO = Path(__file__).resolve().parents[2]


def canonical(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "client.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=600)


def test_canonical_eval_writes_its_results_and_refuses_bad_settings(tmp_path):
    data = write_tsdf_fusion(synthetic_rgbd(num_frames=14, width=40, height=30), tmp_path / "cap")
    out = tmp_path / "out"
    done = canonical("eval", str(data), "--views", "2", "--out", str(out), "--methods", "canonical",
                     "--voxel-size", "0.05", "--stability-views", "none", "--no-extrapolation")
    assert done.returncode == 0, done.stderr
    assert "## Held-out views, clean depth" in done.stdout
    assert json.loads((out / "results.json").read_text())["runs"][0]["method"] == "canonical"
    assert (out / "psnr_vs_views.png").stat().st_size > 0
    refused = canonical("eval", str(data), "--views", "2", "--out", str(out), "--methods", "nerf", "--quiet")
    assert refused.returncode == 2 and "methods" in refused.stderr


def test_canonical_eval_refuses_an_out_it_cannot_write_before_it_runs(tmp_path):
    data = write_tsdf_fusion(synthetic_rgbd(num_frames=14, width=40, height=30), tmp_path / "cap")
    blocker = tmp_path / "file"
    blocker.write_text("")
    for out in (blocker, blocker / "out"):
        refused = canonical("eval", str(data), "--views", "2", "--out", str(out), "--methods", "canonical", "--quiet")
        assert refused.returncode == 2, refused.stderr
        assert refused.stderr.startswith(f"canonical eval: error: --out: cannot write {out}: ")
        assert "Traceback" not in refused.stderr
