"""transforms.json loader on the real shelf frames re-packaged as a nerfstudio capture, the
undistortion on a real image, and the error paths."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from canonical_core.calibration import OPENGL_TO_OPENCV
from canonical_core.datasets import SkippedFrames, load_transforms_json
from canonical_core.datasets.distortion import distort_points, remap, undistort_image, undistort_points
from canonical_core.datasets.images import read_depth, read_rgb

DIST = (-0.12, 0.03, 0.001, -0.0015)  # k1 k2 p1 p2, a typical consumer-lens distortion


def _nerfstudio_frame(f) -> dict:
    """One frames[] entry for a shelf frame: OpenGL camera-to-world (diag(1, -1, -1, 1) is its own inverse)."""
    return {
        "file_path": f"images/{f.frame_id}.png",
        "depth_file_path": f"depth/{f.frame_id}.png",
        "transform_matrix": (f.camera.c2w64() @ OPENGL_TO_OPENCV).tolist(),
    }


def _write_capture(shelf, shelf_path, root, count=3, **top) -> list:
    (root / "images").mkdir(parents=True)
    (root / "depth").mkdir()
    frames = [shelf[i] for i in range(0, 2 * count, 2)]
    for f in frames:
        shutil.copy(shelf_path / "frames" / f"{f.frame_id}.color.png", root / "images" / f"{f.frame_id}.png")
        shutil.copy(shelf_path / "frames" / f"{f.frame_id}.depth.png", root / "depth" / f"{f.frame_id}.png")
    cam = frames[0].camera
    # nerfstudio puts pixel centres at i + 0.5, our K at i: its cx, cy are ours + 0.5
    meta = {"camera_model": "OPENCV", "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx + 0.5, "cy": cam.cy + 0.5,
            "w": 640, "h": 480, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, **top,
            "frames": [_nerfstudio_frame(f) for f in frames]}
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return frames


@pytest.mark.realdata
def test_matches_tsdf_fusion_frames(shelf, shelf_path, tmp_path):
    expected = _write_capture(shelf, shelf_path, tmp_path / "ns")
    seq = load_transforms_json(tmp_path / "ns")
    assert seq.frame_ids == [f.frame_id for f in expected] and seq.name == "ns"
    for a, b in zip(seq, expected):
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth)
        assert np.allclose(a.camera.K64(), b.camera.K64(), atol=1e-9)
        assert np.abs(a.camera.c2w64() - b.camera.c2w64()).max() < 1e-9
    assert len(load_transforms_json(tmp_path / "ns" / "transforms.json", stride=2)) == 2


@pytest.mark.realdata
def test_two_cameras_whose_images_share_names_give_frames_ids_of_their_paths(shelf, shelf_path, tmp_path):
    frames = _write_capture(shelf, shelf_path, tmp_path / "ns", count=2)
    shutil.copytree(tmp_path / "ns" / "images", tmp_path / "ns" / "images_cam2")
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    meta["frames"] += [{**f, "file_path": f["file_path"].replace("images/", "images_cam2/")} for f in meta["frames"]]
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    ids = load_transforms_json(tmp_path / "ns").frame_ids
    assert ids == [f"{folder}/{f.frame_id}" for folder in ("images", "images_cam2") for f in frames]


@pytest.mark.realdata
def test_depth_unit_scale_factor(shelf, shelf_path, tmp_path):
    _write_capture(shelf, shelf_path, tmp_path / "ns", count=1, depth_unit_scale_factor=0.002)
    reference = shelf[0].depth
    assert torch.allclose(load_transforms_json(tmp_path / "ns")[0].depth, 2 * reference)
    assert torch.allclose(load_transforms_json(tmp_path / "ns", depth_unit_scale_factor=1e-3)[0].depth, reference)
    for bad in (1e-12, 1e4, 0, float("inf")):  # said when the capture is opened, naming the factor
        with pytest.raises(ValueError, match="^depth_unit_scale_factor: expected metres per depth unit between"):
            load_transforms_json(tmp_path / "ns", depth_unit_scale_factor=bad)


@pytest.mark.realdata
def test_per_frame_intrinsics_and_camera_angle(shelf, shelf_path, tmp_path):
    _write_capture(shelf, shelf_path, tmp_path / "ns", count=2)
    meta = json.loads((tmp_path / "ns" / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        del meta[key]
    meta["camera_angle_x"] = 2 * math.atan(320 / 500.0)  # instant-ngp style: fl_x = 500
    meta["frames"][1]["fl_x"] = 600.0
    meta["frames"][1]["cx"] = 330.5
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    a, b = load_transforms_json(tmp_path / "ns")
    assert math.isclose(a.camera.fx, 500.0) and math.isclose(a.camera.fy, 500.0)  # fl_y defaults to fl_x
    assert (a.camera.cx, a.camera.cy) == (319.5, 239.5)  # image centre; w, h read from the image
    assert b.camera.fx == 600.0 and b.camera.cx == 330.0
    # a frame's own angle against the file's focal length: the frame's wins, as every per-frame key does
    meta["fl_x"] = 615.0
    meta["frames"][0]["camera_angle_x"] = 2 * math.atan(320 / 450.0)
    (tmp_path / "ns" / "transforms.json").write_text(json.dumps(meta))
    a, b = load_transforms_json(tmp_path / "ns")
    assert math.isclose(a.camera.fx, 450.0) and b.camera.fx == 600.0


@pytest.mark.realdata
def test_undistortion_recovers_a_real_image(shelf_path):
    image = read_rgb(shelf_path / "frames" / "frame-000015.color.png")
    K = np.array([[615.195, 0, 298.443], [0, 615.195, 247.519], [0, 0, 1]])
    H, W = image.shape[:2]
    v, u = np.meshgrid(np.arange(H, dtype=float), np.arange(W, dtype=float), indexing="ij")
    # distorted image: its pixel m shows the scene point whose undistorted pixel is undistort(m)
    xy = undistort_points(np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1), DIST)
    distorted = remap(image, xy[..., 0] * K[0, 0] + K[0, 2], xy[..., 1] * K[1, 1] + K[1, 2], "bilinear")
    restored = undistort_image(distorted, K, DIST, mode="bilinear")
    inner = (slice(40, -40), slice(40, -40))
    error = np.abs(restored[inner].astype(float) - image[inner]).mean()
    untouched = np.abs(distorted[inner].astype(float) - image[inner]).mean()
    assert error < 2.0 and error < 0.2 * untouched  # what is left is two bilinear resamplings


@pytest.mark.realdata
def test_depth_undistortion_invents_no_depth(shelf_path):
    depth = read_depth(shelf_path / "frames" / "frame-000015.depth.png", 1000.0)
    K = np.array([[615.195, 0, 298.443], [0, 615.195, 247.519], [0, 0, 1]])
    out = undistort_image(depth, K, DIST, mode="nearest")
    assert out.dtype == np.float32 and out.shape == depth.shape
    assert np.isin(out, depth).all()  # every value is a copy of an input value (or 0)
    assert (out > 0).mean() > 0.3


def test_points_round_trip_and_identity():
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, (1000, 2))
    assert np.abs(undistort_points(distort_points(xy, DIST), DIST) - xy).max() < 1e-9
    assert np.array_equal(distort_points(xy, (0, 0, 0, 0, 0)), xy)
    with pytest.raises(ValueError, match=r"coeffs: expected 4 or 5 finite numbers"):
        distort_points(xy, (0.1, 0.2))
    with pytest.raises(ValueError, match="mode: expected 'bilinear' or 'nearest'"):
        remap(np.zeros((4, 4)), np.zeros((2, 2)), np.zeros((2, 2)), "cubic")


@pytest.mark.realdata
def test_distorted_capture_is_undistorted_on_load(shelf, shelf_path, tmp_path):
    _write_capture(shelf, shelf_path, tmp_path / "ns", count=1, k1=DIST[0], k2=DIST[1], p1=DIST[2], p2=DIST[3])
    f = load_transforms_json(tmp_path / "ns")[0]
    expected = undistort_image(shelf[0].rgb.numpy(), f.camera.K64(), DIST)
    assert np.array_equal(f.rgb.numpy(), expected)
    assert np.isin(f.depth.numpy(), shelf[0].depth.numpy()).all()
    # the frame's camera without reading it: undistortion keeps K and the image size
    K, c2w, width, height = load_transforms_json(tmp_path / "ns").source(0).view()
    assert np.array_equal(K, f.camera.K64()) and np.array_equal(c2w, f.camera.c2w64())
    assert (width, height) == (f.width, f.height)


@pytest.fixture
def capture(shelf, shelf_path, tmp_path):
    _write_capture(shelf, shelf_path, tmp_path / "ns", count=2)
    return tmp_path / "ns"


def _edit(capture, change):
    meta = json.loads((capture / "transforms.json").read_text())
    change(meta)
    (capture / "transforms.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda m: m.update(frames=[]), "non-empty 'frames' list"),
        (lambda m: m.update(camera_model="OPENCV_FISHEYE"), r"frames\[0\]: camera_model 'OPENCV_FISHEYE' is not supported"),
        (lambda m: [m.pop(k) for k in ("fl_x", "fl_y")], r"frames\[0\]: no focal length"),
        (lambda m: m.update(fl_x="500"), r"frames\[0\]: fl_x must be a finite number"),
        (lambda m: m["frames"][1].pop("transform_matrix"), r"frames\[1\]: no transform_matrix"),
        (lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(0, 3.0), r"frames\[1\]\.transform_matrix: rotation is not orthonormal"),
        (lambda m: m["frames"][1].update(file_path="images/missing.png"), r"missing\.png: file not found \(.*frames\[1\]\.file_path\)"),
        (lambda m: m["frames"][0].update(depth_file_path=7), r"frames\[0\]: depth_file_path must be a non-empty string"),
    ],
)
@pytest.mark.realdata
def test_errors(capture, change, message):
    _edit(capture, change)
    with pytest.raises(ValueError, match=message):
        load_transforms_json(capture, strict=True)


@pytest.mark.realdata
def test_frames_whose_images_are_missing_are_skipped_with_one_warning(shelf, shelf_path, tmp_path):
    """A capture copied in part: the file lists 6 frames, 2 of whose images (one colour, one depth) are
    not there. The loader keeps the 4 others (stride and max_frames count those) and says once how
    many it left out; strict refuses the capture at the first missing file."""
    frames = _write_capture(shelf, shelf_path, tmp_path / "ns", count=6)
    (tmp_path / "ns" / "images" / f"{frames[1].frame_id}.png").unlink()
    (tmp_path / "ns" / "depth" / f"{frames[4].frame_id}.png").unlink()
    kept = [f.frame_id for i, f in enumerate(frames) if i not in (1, 4)]
    with pytest.warns(SkippedFrames) as caught:
        seq = load_transforms_json(tmp_path / "ns")
    assert seq.frame_ids == kept
    assert len(caught) == 1 and "skipped 2 of 6 listed frames" in str(caught[0].message)
    assert f"{frames[1].frame_id}.png: file not found" in str(caught[0].message)
    with pytest.warns(SkippedFrames):
        assert load_transforms_json(tmp_path / "ns", stride=2, max_frames=2).frame_ids == kept[::2]
    with pytest.raises(ValueError, match=rf"{frames[1].frame_id}\.png: file not found \(.*frames\[1\]\.file_path\)"):
        load_transforms_json(tmp_path / "ns", strict=True)
    for f in frames:
        (tmp_path / "ns" / "images" / f"{f.frame_id}.png").unlink(missing_ok=True)
    with pytest.raises(ValueError, match="none of its 6 listed frames has its files"):
        load_transforms_json(tmp_path / "ns")


@pytest.mark.realdata
def test_file_errors(capture, tmp_path):
    with pytest.raises(ValueError, match=r"transforms\.json: file not found"):
        load_transforms_json(tmp_path)
    (capture / "transforms.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"transforms\.json: invalid JSON"):
        load_transforms_json(capture)


@pytest.mark.realdata
def test_size_mismatch_and_extensionless_paths(capture):
    _edit(capture, lambda m: (m.update(w=320), m["frames"][0].update(file_path=m["frames"][0]["file_path"][:-4])))
    seq = load_transforms_json(capture)  # "images/frame-000015" resolves to the .png, as instant-ngp allows
    for read in (lambda: seq[0], seq.source(0).view):  # the frame, and its camera alone
        with pytest.raises(ValueError, match=r"frame-000015\.png: image is 640x480, the capture's are 320x480"):
            read()
