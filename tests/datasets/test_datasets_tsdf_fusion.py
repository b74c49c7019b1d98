"""tsdf-fusion / 7-Scenes loader on the real shelf capture, the writer, and the error paths."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from canonical_core import Camera, Frame
from canonical_core.datasets import FrameSequence, SkippedFrames, load_tsdf_fusion, synthetic_rgbd, write_tsdf_fusion

SHELF_K = [[615.1951904296875, 0, 298.44268798828125], [0, 615.19525146484375, 247.51919555664062], [0, 0, 1]]


@pytest.mark.realdata
def test_shelf_listing(shelf):
    assert isinstance(shelf, FrameSequence)
    assert len(shelf) == 50 and shelf.name == "realsense_shelf"
    assert shelf.frame_ids[0] == "frame-000015" and shelf.frame_ids[-1] == "frame-000113"
    assert shelf.frame_ids == [f"frame-{n:06d}" for n in range(15, 114, 2)]


@pytest.mark.realdata
def test_shelf_first_frame(shelf):
    f = shelf[0]
    assert f.frame_id == "frame-000015"
    assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == torch.uint8
    assert f.depth.shape == (480, 640) and f.depth.dtype == torch.float32
    assert np.allclose(f.camera.K64(), SHELF_K)
    assert np.allclose(f.camera.c2w64(), np.eye(4))
    missing = float((f.depth == 0).float().mean())
    assert 0.6 < missing < 0.72  # README: about 66 % holes
    valid = f.depth[f.depth > 0]
    assert 0.38 < float(valid.median()) < 0.44  # README: median about 0.41 m
    assert 0.05 < float(valid.min()) and float(valid.max()) < 1.5


@pytest.mark.realdata
def test_shelf_pose_convention_end_to_end(shelf, reprojection_error):
    # frame 15 lifted into frame 45: the README measures a 2.3 mm median depth error
    assert shelf.frame_ids[15] == "frame-000045"
    error, count = reprojection_error(shelf[0], shelf[15])
    assert count > 10_000
    assert error < 0.005


@pytest.mark.realdata
def test_shelf_stride_and_max_frames(shelf_path):
    seq = load_tsdf_fusion(shelf_path, stride=10, max_frames=3)
    assert seq.frame_ids == ["frame-000015", "frame-000035", "frame-000055"]
    assert len(load_tsdf_fusion(shelf_path, stride=7)) == 8


@pytest.mark.realdata
def test_explicit_intrinsics_override(shelf_path):
    seq = load_tsdf_fusion(shelf_path, intrinsics=(585, 585, 320, 240), max_frames=1)
    assert seq[0].camera.fx == 585 and seq[0].camera.cx == 320


def test_write_read_round_trip(tmp_path):
    frames = synthetic_rgbd(num_frames=4, width=80, height=60, seed=3)
    folder = write_tsdf_fusion(frames, tmp_path / "out")
    assert (folder / "camera-intrinsics.txt").is_file()
    seq = load_tsdf_fusion(folder)
    assert seq.frame_ids == [f"frame-{i:06d}" for i in range(4)]
    for a, b in zip(frames, seq):
        assert torch.equal(a.rgb, b.rgb)
        assert np.array_equal(a.camera.K64(), b.camera.K64())
        assert np.abs(a.camera.c2w64() - b.camera.c2w64()).max() < 1e-6
        assert float((a.depth - b.depth).abs().max()) <= 0.001
        assert torch.equal(a.depth > 0, b.depth > 0)


def test_writer_refuses_bad_input(tmp_path, tiny_tsdf):
    f = synthetic_rgbd(num_frames=1, width=16, height=12)[0]
    with pytest.raises(ValueError, match="already holds frame"):
        write_tsdf_fusion([f], tiny_tsdf)
    with pytest.raises(ValueError, match=r"frames\[0\].*has no depth"):
        write_tsdf_fusion([Frame(rgb=f.rgb, camera=f.camera)], tmp_path / "a")
    other = Camera([[20, 0, 8], [0, 20, 6], [0, 0, 1]], np.eye(4), 16, 12)
    with pytest.raises(ValueError, match=r"frames\[1\].*differs"):
        write_tsdf_fusion([f, Frame(rgb=f.rgb, camera=other, depth=f.depth)], tmp_path / "b")
    with pytest.raises(ValueError, match="does not fit"):
        write_tsdf_fusion([Frame(rgb=f.rgb, camera=f.camera, depth=torch.full((12, 16), 70.0))], tmp_path / "c")
    with pytest.raises(ValueError, match="empty"):
        write_tsdf_fusion([], tmp_path / "d")


@pytest.fixture
def capture(tmp_path, tiny_tsdf):
    return shutil.copytree(tiny_tsdf, tmp_path / "cap")


def test_error_not_a_folder(tmp_path):
    with pytest.raises(ValueError, match="not a folder"):
        load_tsdf_fusion(tmp_path / "nope")
    with pytest.raises(ValueError, match=r"no frame-\*\.pose\.txt"):
        load_tsdf_fusion(tmp_path)


@pytest.mark.parametrize("scale", [1e-9, float("inf"), 0])
def test_a_depth_scale_out_of_range_is_refused_when_the_capture_is_opened(capture, scale):
    with pytest.raises(ValueError, match="^depth_scale: expected depth units per metre between"):
        load_tsdf_fusion(capture, depth_scale=scale)


def test_error_missing_intrinsics(capture):
    (capture / "camera-intrinsics.txt").unlink()
    with pytest.raises(ValueError, match="intrinsics="):
        load_tsdf_fusion(capture)
    assert len(load_tsdf_fusion(capture, intrinsics=(50, 50, 32, 24))) == 3


def test_error_missing_colour_and_depth(capture):
    (capture / "frame-000001.color.png").unlink()
    with pytest.raises(ValueError, match=r"frame-000001\.color\.png: file not found"):
        load_tsdf_fusion(capture, strict=True)
    with pytest.warns(SkippedFrames, match=r"skipped 1 of 3 listed frames .*frame-000001\.color\.png: file not found"):
        assert load_tsdf_fusion(capture).frame_ids == ["frame-000000", "frame-000002"]
    shutil.copy(capture / "frame-000000.color.png", capture / "frame-000001.color.png")
    (capture / "frame-000002.depth.png").unlink()
    with pytest.raises(ValueError, match=r"frame-000002\.depth\.png: file not found"):
        load_tsdf_fusion(capture, strict=True)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1 0 0\n0 1 0\n", "expected 16 numbers, got 6"),
        ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 x\n", "could not convert"),
        ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not orthonormal"),
        ("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n", "determinant"),
        ("1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "NaN"),
    ],
)
def test_error_malformed_pose(capture, text, message):
    (capture / "frame-000001.pose.txt").write_text(text)
    with pytest.raises(ValueError, match=rf"frame-000001\.pose\.txt.*{message}"):
        load_tsdf_fusion(capture)


def test_error_unreadable_and_mismatched_images(capture):
    (capture / "frame-000000.color.png").write_bytes(b"not a png")
    (capture / "frame-000001.depth.png").unlink()
    Image.fromarray(np.zeros((24, 30), np.uint16)).save(capture / "frame-000001.depth.png")
    Image.fromarray(np.zeros((48, 64), np.uint8)).save(capture / "frame-000002.depth.png")
    with pytest.raises(ValueError, match=r"frame-000000\.color\.png: unreadable image"):
        load_tsdf_fusion(capture)  # listing reads the first frame's image header: the capture's size
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(capture / "frame-000000.color.png")
    seq = load_tsdf_fusion(capture)
    Image.fromarray(np.zeros((50, 64, 3), np.uint8)).save(capture / "frame-000000.color.png")
    with pytest.raises(ValueError, match=r"frame-000000\.color\.png: image is 64x50, the capture's are 64x48"):
        seq.source(0).view()  # a frame of another size than the first: the intrinsics are not this image's
    with pytest.raises(ValueError, match=r"frame-000000\.color\.png: image is 64x50, the capture's are 64x48"):
        seq[0]  # the colour image's size is the problem: named before its depth is compared with it
    with pytest.raises(ValueError, match=r"frame-000001\.depth\.png: depth size 30x24 does not match.*64x48.*: .*field of view"):
        seq[1]
    with pytest.raises(ValueError, match=r"frame-000002\.depth\.png: expected a 16-bit"):
        seq[2]


def test_depth_at_a_lower_resolution_loads_at_its_pixels(capture):
    # a phone's or a time-of-flight camera's depth, registered to the colour camera at half its size
    depth = np.asarray(Image.open(capture / "frame-000001.depth.png"))
    Image.fromarray(np.ascontiguousarray(depth[::2, ::2])).save(capture / "frame-000001.depth.png")
    full, half = load_tsdf_fusion(capture)[0], load_tsdf_fusion(capture)[1]
    assert half.rgb.shape[:2] == half.depth.shape == (full.height // 2, full.width // 2)
    assert half.camera.fx == pytest.approx(full.camera.fx / 2)


def test_frames_in_subfolder_and_ambiguity(tmp_path, tiny_tsdf):
    shutil.copytree(tiny_tsdf, tmp_path / "root" / "frames")
    shutil.move(tmp_path / "root" / "frames" / "camera-intrinsics.txt", tmp_path / "root" / "intrinsics.K.txt")
    assert len(load_tsdf_fusion(tmp_path / "root")) == 3
    shutil.copytree(tiny_tsdf, tmp_path / "root" / "more")
    with pytest.raises(ValueError, match="several subfolders"):
        load_tsdf_fusion(tmp_path / "root")


def test_seven_scenes_invalid_depth_code(capture):
    raw = np.array(Image.open(capture / "frame-000000.depth.png"))
    raw[:4] = 65535  # 7-Scenes marks invalid depth with 65535
    Image.fromarray(raw).save(capture / "frame-000000.depth.png")
    depth = load_tsdf_fusion(capture)[0].depth
    assert (depth[:4] == 0).all() and float(depth.max()) < 65
