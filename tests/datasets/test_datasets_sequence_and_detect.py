"""FrameSequence behaviour, layout detection, and the shared PGM / depth readers."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from canonical_core.datasets import FrameSequence, MissingIntrinsics, load_dataset, synthetic_rgbd, write_tsdf_fusion
from canonical_core.datasets.images import DEPTH_INVALID_CODE, depth_from_uint16, read_depth, read_pgm


REPO = Path(__file__).resolve().parents[2]


@pytest.mark.realdata
@pytest.mark.parametrize("capture", ["realsense_shelf", "apc_bins/bin_labels"])
def test_a_capture_is_listed_without_torch_and_its_first_frame_loads_it(shelf_dir, capture):
    # a client that sends a capture's files as they are starts without loading torch (`sequence`)
    probe = ("import sys; from canonical_core.datasets import load_dataset; "
             f"seq = load_dataset({str(shelf_dir.parent / capture)!r}); "
             "source = seq.source(0); before = 'torch' in sys.modules; frame = seq[0]; "
             "print(len(seq) > 1, source.frame_id == frame.frame_id, before, 'torch' in sys.modules, tuple(frame.rgb.shape))")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True", "False", "True", "(480,", "640,", "3)"]


def _views_match_loaded_cameras(seq) -> None:
    for i in (0, len(seq) - 1):
        K, c2w, width, height = seq.source(i).view()
        camera = seq[i].camera
        assert np.array_equal(K, camera.K64()) and np.array_equal(c2w, camera.c2w64())
        assert (width, height) == (camera.width, camera.height)


def test_a_frames_view_is_the_camera_its_load_gives(tiny_tsdf):
    _views_match_loaded_cameras(load_dataset(tiny_tsdf))
    _views_match_loaded_cameras(synthetic_rgbd(num_frames=2, width=40, height=30))


@pytest.mark.realdata
def test_a_real_frames_view_is_the_camera_its_load_gives(shelf_path):
    _views_match_loaded_cameras(load_dataset(shelf_path))
    _views_match_loaded_cameras(load_dataset(shelf_path.parent / "apc_bins" / "bin_labels"))  # label-fusion frames


def test_a_view_checks_the_intrinsics_against_the_image_it_reads(tiny_tsdf, tmp_path):
    capture = tmp_path / "cap"
    shutil.copytree(tiny_tsdf, capture)
    (capture / "camera-intrinsics.txt").write_text("500 0 2000\n0 500 24\n0 0 1\n")  # cx far right of 64 pixels
    seq = load_dataset(capture)
    with pytest.raises(ValueError, match="principal point"):
        seq.source(0).view()
    with pytest.raises(ValueError, match="principal point"):
        seq[0]


def test_sequence_indexing(tiny_tsdf):
    seq = load_dataset(tiny_tsdf)
    assert len(seq) == 3 and seq[-1].frame_id == seq[2].frame_id == "frame-000002"
    assert seq[np.int64(1)].frame_id == "frame-000001"
    part = seq[::2]
    assert isinstance(part, FrameSequence) and part.frame_ids == ["frame-000000", "frame-000002"]
    assert part.name == seq.name and "3 frames" in repr(seq)
    assert [f.frame_id for f in seq] == seq.frame_ids
    with pytest.raises(IndexError, match="frame index 3 out of range for 3 frames"):
        seq[3]
    with pytest.raises(IndexError):
        seq[-4]
    with pytest.raises(TypeError):
        seq["0"]


def test_sequence_is_lazy(tiny_tsdf, tmp_path):
    copy = shutil.copytree(tiny_tsdf, tmp_path / "cap")
    seq = load_dataset(copy)
    for png in copy.glob("*.png"):
        png.unlink()
    assert seq.frame_ids == ["frame-000000", "frame-000001", "frame-000002"]  # no image needed
    with pytest.raises(ValueError, match=r"frame-000001\.color\.png: file not found"):
        seq[1]


@pytest.mark.realdata
def test_detect_and_dispatch(shelf_path, slambook_path, slambook_K, tiny_tsdf):
    assert load_dataset(shelf_path, max_frames=2).frame_ids == ["frame-000015", "frame-000017"]
    assert load_dataset(slambook_path, K=slambook_K).frame_ids == ["1", "2", "3", "4", "5"]
    assert len(load_dataset(tiny_tsdf, stride=2)) == 2


@pytest.mark.realdata
def test_one_K_gives_the_intrinsics_of_every_layout_that_reads_them(shelf_path, slambook_path, slambook_K, tiny_tsdf,
                                                                     tmp_path):
    with pytest.raises(MissingIntrinsics, match="slambook_rgbd5: camera intrinsics are needed"):
        load_dataset(slambook_path)
    assert load_dataset(slambook_path, K=slambook_K)[0].camera.fx == slambook_K[0]
    assert load_dataset(shelf_path, max_frames=1, K=(600, 601, 320, 240))[0].camera.fy == 601  # in place of its own
    bare = shutil.copytree(tiny_tsdf, tmp_path / "bare")
    for intrinsics in bare.glob("*intrinsics*"):
        intrinsics.unlink()
    with pytest.raises(MissingIntrinsics, match="no intrinsics file"):
        load_dataset(bare)
    assert load_dataset(bare, K=np.array([[20.0, 0, 32], [0, 20, 24], [0, 0, 1]]))[0].camera.fx == 20.0
    (tmp_path / "transforms.json").write_text('{"fl_x": 12.8, "w": 16, "h": 12, "frames": []}')
    with pytest.raises(ValueError, match="^K: a transforms_json capture's frames carry their own intrinsics"):
        load_dataset(tmp_path / "transforms.json", K=slambook_K)


def test_detect_transforms_json(tmp_path):
    seq = write_tsdf_fusion(synthetic_rgbd(num_frames=1, width=16, height=12), tmp_path)
    (tmp_path / "transforms.json").write_text(
        '{"fl_x": 12.8, "w": 16, "h": 12, "frames": [{"file_path": "frame-000000.color.png", '
        '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}'
    )
    for path in (seq, tmp_path / "transforms.json"):
        f = load_dataset(path)[0]
        assert f.frame_id == "frame-000000.color" and f.depth is None  # transforms.json wins
        assert np.allclose(f.camera.c2w64(), np.diag([1.0, -1, -1, 1]))  # OpenGL -> OpenCV


def test_nothing_matches(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match=rf"{tmp_path}: no known capture layout"):
        load_dataset(tmp_path)
    with pytest.raises(ValueError, match="not a folder or a transforms.json"):
        load_dataset(tmp_path / "missing")


def _pgm(path, values, maxval, comment=b""):
    dtype = ">u2" if maxval > 255 else "u1"
    h, w = values.shape
    path.write_bytes(b"P5\n" + comment + b"%d %d\n%d\n" % (w, h, maxval) + values.astype(dtype).tobytes())


def test_pgm_keeps_raw_values(tmp_path):
    # Pillow 13 rescales samples to 0..65535 when maxval is not 65535; depth must stay in raw units
    values = np.array([[0, 1000, 4095], [300, 1, 2]])
    _pgm(tmp_path / "d.pgm", values, 4095, comment=b"# a comment\n")
    assert read_pgm(tmp_path / "d.pgm").tolist() == values.tolist()
    assert np.allclose(read_depth(tmp_path / "d.pgm", 1000.0), values / 1000.0)
    _pgm(tmp_path / "b.pgm", np.array([[7, 255]]), 255)
    assert read_pgm(tmp_path / "b.pgm").tolist() == [[7, 255]]


@pytest.mark.parametrize("depth_scale", [1000.0, 5000.0, 10000.0, 4000.0, 1.0, 3.7, 1e-3])
def test_depth_from_uint16_is_the_float64_division_rounded_to_float32(depth_scale):
    """The one-pass kernel against its definition, on every 16-bit value (a strided view too)."""
    raw = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    expected = raw.astype(np.float64) / depth_scale
    expected[(raw == 0) | (raw == DEPTH_INVALID_CODE)] = 0.0
    expected = expected.astype(np.float32)
    got = depth_from_uint16(raw, depth_scale)
    assert got.dtype == np.float32 and got.shape == raw.shape
    assert np.array_equal(got.view(np.uint32), expected.view(np.uint32))
    assert np.array_equal(depth_from_uint16(raw[:, ::3], depth_scale).view(np.uint32), expected[:, ::3].view(np.uint32))


def test_pgm_and_depth_errors(tmp_path):
    (tmp_path / "t.pgm").write_bytes(b"P5\n4 4\n65535\n" + b"\x00" * 10)
    with pytest.raises(ValueError, match=r"t\.pgm: truncated PGM"):
        read_pgm(tmp_path / "t.pgm")
    (tmp_path / "a.pgm").write_bytes(b"P2\n1 1\n255\n7\n")
    with pytest.raises(ValueError, match=r"a\.pgm: not a binary PGM"):
        read_pgm(tmp_path / "a.pgm")
    with pytest.raises(ValueError, match=r"x\.pgm: file not found"):
        read_depth(tmp_path / "x.pgm", 1000.0)
    for scale in (0, 1e-300, float("nan")):  # near 0 every code would lie at an infinite depth
        with pytest.raises(ValueError, match=f"depth_scale: expected depth units per metre .* got {scale}"):
            read_depth(tmp_path / "a.pgm", scale)
    Image.new("RGB", (2, 2)).save(tmp_path / "c.png")
    with pytest.raises(ValueError, match=r"c\.png: expected a 16-bit single-channel depth image, got PIL mode 'RGB'"):
        read_depth(tmp_path / "c.png", 1000.0)


def test_a_depth_scale_given_replaces_the_layouts_where_its_depth_has_none(tmp_path):
    root = write_tsdf_fusion(synthetic_rgbd(num_frames=2, width=40, height=30), tmp_path / "cap")  # millimetres
    own, halved = load_dataset(root)[1].depth.numpy(), load_dataset(root, depth_scale=2000)[1].depth.numpy()
    assert np.allclose(halved, own / 2, atol=1e-6) and own.max() > 0
    for scale in (0, 1e-300, float("nan")):  # 1e-300: every code infinitely far
        with pytest.raises(ValueError, match=rf"depth_scale: expected depth units per metre between 0.001 and 1e\+09 .*, got {scale}"):
            load_dataset(root, depth_scale=scale)
    for color in root.rglob("frame-*.color.png"):  # label maps beside the frames: a label-fusion capture
        Image.fromarray(np.zeros((30, 40), np.uint8)).save(color.with_name(color.name.replace(".color.", ".mask.")))
    with pytest.raises(ValueError, match="depth_scale: a label_fusion capture's depth carries its own scale"):
        load_dataset(root, depth_scale=1000)
