"""TUM-style loader: the real slambook capture (PGM depth, pose.txt), a TUM RGB-D timestamp layout
built from it, and the error paths."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image

from canonical_core import Camera
from canonical_core.datasets import SkippedFrames, load_tum
from canonical_core.datasets.images import read_pgm

pytestmark = pytest.mark.realdata


def test_slambook_listing_and_frames(slambook):
    assert len(slambook) == 5 and slambook.frame_ids == ["1", "2", "3", "4", "5"]
    f = slambook[0]
    assert f.rgb.shape == (480, 640, 3) and f.depth.shape == (480, 640)
    assert (f.camera.fx, f.camera.fy, f.camera.cx, f.camera.cy) == (518.0, 519.0, 325.5, 253.5)
    # first pose line: -0.228993 0.00645704 0.0287837 ... (camera-to-world translation)
    assert np.allclose(f.camera.c2w64()[:3, 3], [-0.228993, 0.00645704, 0.0287837])


def test_slambook_depth_is_big_endian_millimetres(slambook, slambook_path):
    data = (slambook_path / "depth" / "1.pgm").read_bytes()
    assert data.startswith(b"P5")
    raw = np.frombuffer(data[-640 * 480 * 2 :], ">u2").reshape(480, 640)  # maxval 65535: 2 bytes a sample
    depth = slambook[0].depth.numpy()
    assert np.allclose(depth, raw / 1000.0, atol=1e-6)
    valid = depth[depth > 0]
    assert valid.size > 100_000
    assert 0.3 < valid.min() and valid.max() < 12 and 1.5 < np.median(valid) < 5  # a room, in metres


def test_slambook_poses_are_camera_to_world(slambook, reprojection_error):
    # poses are rough (2-10 cm): consecutive frames agree to several cm; read as world-to-camera
    # instead, the same check is off by metres, so the test tells the conventions apart
    frames = list(slambook)
    errors = [reprojection_error(a, b)[0] for a, b in zip(frames, frames[1:])]
    assert max(errors) < 0.15 and np.median(errors) < 0.10

    def as_w2c(f):
        cam = Camera.from_w2c(f.camera.K, f.camera.c2w64(), f.width, f.height)
        return type(f)(rgb=f.rgb, camera=cam, depth=f.depth)

    wrong = [reprojection_error(as_w2c(a), as_w2c(b))[0] for a, b in zip(frames, frames[1:])]
    assert np.median(wrong) > 3 * np.median(errors)


def test_slambook_stride_max_frames(slambook_path, slambook_K):
    assert load_tum(slambook_path, K=slambook_K, stride=2).frame_ids == ["1", "3", "5"]
    assert load_tum(slambook_path, K=slambook_K, max_frames=2).frame_ids == ["1", "2"]
    with pytest.raises(ValueError, match="stride: expected a positive integer, got 0"):
        load_tum(slambook_path, K=slambook_K, stride=0)


def test_k_is_required(slambook_path, tmp_path):
    with pytest.raises(ValueError, match=r"slambook_rgbd5: camera intrinsics are needed \(the capture has none\): pass K="):
        load_tum(slambook_path)
    copy = shutil.copytree(slambook_path, tmp_path / "sb")
    (copy / "intrinsics.txt").write_text("518 0 325.5\n0 519 253.5\n0 0 1\n")
    assert load_tum(copy)[0].camera.fy == 519.0
    with pytest.raises(ValueError, match="K: expected a 3x3 matrix or"):
        load_tum(copy, K=(1, 2, 3))


@pytest.fixture
def tum_layout(tmp_path, slambook_path):
    """The slambook frames rewritten in the TUM RGB-D layout: timestamped lists, 1/5000 m PNG
    depth, a 100 Hz groundtruth, a depth stream offset by 5 ms, and one colour image (the 6th)
    that has no depth within 0.02 s."""
    root = tmp_path / "rgbd_dataset_test"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    poses = [line.split() for line in (slambook_path / "pose.txt").read_text().split("\n") if line.strip()]
    rgb_lines, depth_lines, gt_lines = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for k in range(1, 6):
        t = 1305031102.0 + k * 0.5
        shutil.copy(slambook_path / "color" / f"{k}.png", root / "rgb" / f"{t:.6f}.png")
        mm = read_pgm(slambook_path / "depth" / f"{k}.pgm")
        Image.fromarray((mm.astype(np.uint32) * 5).astype(np.uint16)).save(root / "depth" / f"{t + 0.005:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth_lines.append(f"{t + 0.005:.6f} depth/{t + 0.005:.6f}.png")
        gt_lines.append(f"{t - 0.3:.4f} 9 9 9 0 0 0 1")  # a far-off pose that must not be picked
        gt_lines.append(f"{t + 0.003:.4f} " + " ".join(poses[k - 1]))
    t6 = 1305031102.0 + 3.0
    shutil.copy(slambook_path / "color" / "1.png", root / "rgb" / f"{t6:.6f}.png")
    rgb_lines.append(f"{t6:.6f} rgb/{t6:.6f}.png")
    gt_lines.append(f"{t6:.4f} 0 0 0 0 0 0 1")
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("groundtruth.txt", gt_lines)):
        (root / name).write_text("\n".join(lines) + "\n")
    return root


def test_tum_timestamp_layout(tum_layout, slambook, slambook_K):
    with pytest.warns(SkippedFrames, match=r"rgb\.txt: skipped 1 of 6 colour images, which have no depth image or pose"):
        seq = load_tum(tum_layout, K=slambook_K)
    with pytest.raises(ValueError, match=r"rgb\.txt: 1 of 6 colour images, which have no depth image or pose .*strict"):
        load_tum(tum_layout, K=slambook_K, strict=True)
    assert seq.frame_ids == [f"{1305031102.0 + k * 0.5:.6f}" for k in range(1, 6)]  # 6th dropped: no depth
    for a, b in zip(seq, slambook):
        assert np.array_equal(a.rgb.numpy(), b.rgb.numpy())
        assert np.allclose(a.depth.numpy(), b.depth.numpy(), atol=1e-6)  # default TUM scale 5000
        assert np.allclose(a.camera.c2w64(), b.camera.c2w64(), atol=1e-9)
    with pytest.raises(ValueError, match="no colour image has both a depth image and a pose within 0.001 s"):
        load_tum(tum_layout, K=slambook_K, max_dt=0.001)


def test_tum_errors(tum_layout, slambook_K):
    lines = (tum_layout / "groundtruth.txt").read_text().splitlines()
    (tum_layout / "groundtruth.txt").write_text("\n".join(lines[:3] + ["1305031102.5 1 2 3 0 0 1"] + lines[4:]))
    with pytest.raises(ValueError, match=r"groundtruth\.txt:4: expected 8 columns, got 7"):
        load_tum(tum_layout, K=slambook_K)
    with pytest.raises(ValueError, match="depth_scale: expected depth units per metre"):
        load_tum(tum_layout, K=slambook_K, depth_scale=1e-300)  # every code at an infinite depth
    (tum_layout / "groundtruth.txt").write_text("\n".join(lines[:3] + ["1305031102.501 1 2 3 0 0 0 0"] + lines[4:]))
    with pytest.raises(ValueError, match=r"groundtruth\.txt:4: expected finite values and a non-zero quaternion"):
        load_tum(tum_layout, K=slambook_K)
    (tum_layout / "groundtruth.txt").write_text("\n".join(lines))
    colour = (tum_layout / "rgb.txt").read_text().splitlines()
    (tum_layout / "rgb.txt").write_text("\n".join(colour[:-1]) + "\n")  # without the 6th: strict would refuse it
    next((tum_layout / "depth").iterdir()).unlink()
    with pytest.raises(ValueError, match=r"\.png: file not found \(listed at .*depth\.txt:\d+\)"):
        load_tum(tum_layout, K=slambook_K, strict=True)
    with pytest.warns(SkippedFrames, match=r"rgb\.txt: skipped 1 of 5 listed frames"):
        assert len(load_tum(tum_layout, K=slambook_K)) == 4
    (tum_layout / "rgb.txt").unlink()
    with pytest.raises(ValueError, match=r"rgb\.txt: file not found"):
        load_tum(tum_layout, K=slambook_K)


def test_slambook_errors(slambook_path, slambook_K, tmp_path):
    copy = shutil.copytree(slambook_path, tmp_path / "sb")
    lines = (copy / "pose.txt").read_text().splitlines()
    (copy / "pose.txt").write_text("\n".join(lines[:2] + ["1 2 3 x 0 0 1"] + lines[3:]))
    with pytest.raises(ValueError, match=r"pose\.txt:3: could not convert"):
        load_tum(copy, K=slambook_K)
    (copy / "pose.txt").write_text("\n".join(lines))
    (copy / "color" / "4.png").unlink()
    with pytest.raises(ValueError, match=r"color/4\.png: file not found \(colour image of pose line 4"):
        load_tum(copy, K=slambook_K, strict=True)
    with pytest.warns(SkippedFrames, match=r"pose\.txt: skipped 1 of 5 listed frames"):
        assert load_tum(copy, K=slambook_K).frame_ids == ["1", "2", "3", "5"]
    shutil.copy(copy / "color" / "1.png", copy / "color" / "4.png")
    Image.new("RGB", (320, 240)).save(copy / "color" / "2.png")
    # the colour image is the one of another size than the capture's: named, not its depth
    with pytest.raises(ValueError, match=r"color/2\.png: image is 320x240, the capture's are 640x480"):
        load_tum(copy, K=slambook_K)[1]
    (copy / "pose.txt").unlink()
    with pytest.raises(ValueError, match="neither groundtruth.txt"):
        load_tum(copy, K=slambook_K)
