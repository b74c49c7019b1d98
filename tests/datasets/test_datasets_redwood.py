"""The Redwood / Open3D loader: the synthetic living room (poses held by a depth warp), detection,
and the errors of a malformed trajectory."""

from __future__ import annotations

import shutil

import pytest

from canonical_core.datasets import load_dataset, load_redwood
from canonical_core.datasets.detect import detect_layout
from canonical_core.datasets.redwood import read_trajectory_log


def test_the_living_room_loads_with_poses_that_warp_depth_onto_the_next_frame(livingroom_path, reprojection_error):
    seq = load_redwood(livingroom_path)
    assert len(seq) == 211 and seq.frame_ids[:2] == ["00000", "00001"]
    a, b = seq[100], seq[102]
    assert tuple(a.rgb.shape) == (480, 640, 3) and (a.camera.fx, a.camera.cx) == (525.0, 319.5)
    error, compared = reprojection_error(a, b)
    assert compared > 100_000 and error < 0.02  # the capture's README: about 1 mm


def test_load_dataset_detects_the_layout_and_takes_other_intrinsics(livingroom_path):
    assert detect_layout(livingroom_path) == "redwood"
    seq = load_dataset(livingroom_path, stride=100, intrinsics=(500.0, 501.0, 320.0, 240.0))
    assert seq.frame_ids == ["00000", "00100", "00200"] and seq[0].camera.fy == 501.0


def test_a_trajectory_that_does_not_match_the_images_is_refused(livingroom_path, tmp_path):
    root = tmp_path / "room3"
    (root / "image").mkdir(parents=True)
    for name in ("00000.jpg", "00001.jpg", "00002.jpg"):
        shutil.copy(livingroom_path / "image" / name, root / "image")
    log = (livingroom_path / "trajectory.log").read_text().splitlines()
    (root / "trajectory.log").write_text("\n".join(log[:10]) + "\n")
    with pytest.raises(ValueError, match=r"trajectory\.log: 2 poses for 3 images"):
        load_redwood(root)
    (root / "trajectory.log").write_text("\n".join(log[:14]) + "\n")
    with pytest.raises(ValueError, match=r"trajectory\.log: 14 non-empty lines; expected 5 per frame"):
        read_trajectory_log(root / "trajectory.log")
    (root / "trajectory.log").write_text("\n".join([*log[:13], "0 0 1", *log[14:15]]) + "\n")
    with pytest.raises(ValueError, match=r"trajectory\.log:12: expected 4 rows of 4 numbers"):
        read_trajectory_log(root / "trajectory.log")
    (root / "trajectory.log").write_text("\n".join(log[:15]) + "\n")
    assert [f.depth is None for f in load_redwood(root)] == [True, True, True]  # no depth/ folder: RGB only
