"""The deep-video-mvs loader: the real office walk (poses held by a depth warp), detection, and the
errors of a malformed folder."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from canonical_core.datasets import load_dataset, load_deep_video_mvs
from canonical_core.datasets.detect import detect_layout


def test_the_office_walk_loads_with_poses_that_warp_depth_onto_the_next_frame(hololens_path, reprojection_error):
    seq = load_deep_video_mvs(hololens_path)
    assert len(seq) == 187 and seq.frame_ids[:2] == ["00003", "00005"]
    a, b = seq[40], seq[41]
    assert tuple(a.rgb.shape) == (360, 540, 3) and a.camera.fx == pytest.approx(495.5677570093)
    assert 0.3 < float(a.depth[a.depth > 0].median()) < 5.0  # millimetres read as metres
    error, compared = reprojection_error(a, b)
    assert compared > 10_000 and error < 0.02  # the capture's README: 3-13 mm between kept frames


def test_load_dataset_detects_the_layout(hololens_path):
    assert detect_layout(hololens_path) == "deep_video_mvs"
    assert load_dataset(hololens_path, stride=50).frame_ids == ["00003", "00103", "00203", "00305"]  # the walk skips a few frame numbers


@pytest.fixture()
def small_copy(hololens_path, tmp_path):
    """The first three frames of the office walk, as their own deep-video-mvs folder."""
    root = tmp_path / "office3"
    (root / "images").mkdir(parents=True)
    (root / "depth").mkdir()
    shutil.copy(hololens_path / "K.txt", root)
    names = sorted(p.name for p in (hololens_path / "images").iterdir())[:3]
    for name in names:
        shutil.copy(hololens_path / "images" / name, root / "images")
        shutil.copy(hololens_path / "depth" / name, root / "depth")
    (root / "poses.txt").write_text("\n".join((hololens_path / "poses.txt").read_text().splitlines()[:3]) + "\n")
    return root


def test_a_frame_without_its_depth_file_is_rgb_only(small_copy):
    (small_copy / "depth" / "00005.png").unlink()
    with pytest.warns(UserWarning, match=r"depth: 1 of 3 images have no depth image of their name \(the first: 00005\)"):
        seq = load_deep_video_mvs(small_copy)
    assert [f.depth is None for f in seq] == [False, True, False]


def test_malformed_folders_name_the_file_and_the_problem(small_copy, tmp_path):
    lines = (small_copy / "poses.txt").read_text().splitlines()
    (small_copy / "poses.txt").write_text("\n".join(lines[:2]) + "\n")
    with pytest.raises(ValueError, match=r"poses\.txt: 2 poses for 3 images"):
        load_deep_video_mvs(small_copy)
    (small_copy / "poses.txt").write_text("\n".join([*lines[:2], " ".join(lines[2].split()[:12])]) + "\n")
    with pytest.raises(ValueError, match=r"poses\.txt:3: expected the 16 numbers of a 4x4 matrix, got 12"):
        load_deep_video_mvs(small_copy)
    flipped = np.array(lines[2].split(), float).reshape(4, 4)
    flipped[:3, 0] *= -1  # a reflection: det -1
    (small_copy / "poses.txt").write_text("\n".join([*lines[:2], " ".join(map(str, flipped.ravel()))]) + "\n")
    with pytest.raises(ValueError, match=r"poses\.txt:3"):
        load_deep_video_mvs(small_copy)
    with pytest.raises(ValueError, match="not a deep-video-mvs folder"):
        load_deep_video_mvs(tmp_path)
    (small_copy / "poses.txt").write_text("\n".join(lines) + "\n")
    for scale in (0, 1e-300):  # near 0 every code would lie at an infinite depth
        with pytest.raises(ValueError, match="depth_scale: expected depth units per metre"):
            load_deep_video_mvs(small_copy, depth_scale=scale)


def test_images_named_without_zero_padding_take_their_poses_in_numeric_order(small_copy):
    for k, name in enumerate(sorted(p.name for p in (small_copy / "images").iterdir()), start=1):
        for folder in ("images", "depth"):  # 00003.png ... -> 1.png, 2.png, then 10.png last
            (small_copy / folder / name).rename(small_copy / folder / f"{10 if k == 3 else k}.png")
    seq = load_deep_video_mvs(small_copy)
    poses = (small_copy / "poses.txt").read_text().splitlines()
    assert seq.frame_ids == ["1", "2", "10"]  # not "1", "10", "2": pose k belongs to the k-th image
    assert np.allclose(seq[2].camera.c2w64(), np.array(poses[2].split(), float).reshape(4, 4))
