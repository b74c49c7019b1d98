"""The viewer's pictures of rendered maps and its camera track file, on hand-made arrays."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from canonical_core import Camera
from server import wire
from server.track import CAMERA_COLUMNS, camera_json, camera_row, read_track
from server.viewer import (COVERED, DEPTH_LUT, PALETTE, UNCOVERED, centre_depth, coverage_picture, depth_picture,
                           depth_range, label_picture, visible_labels)


def test_depth_lut_is_injective_and_darkens_with_depth():
    assert len({tuple(c) for c in DEPTH_LUT}) == 256
    luma = DEPTH_LUT.astype(float) @ [0.299, 0.587, 0.114]
    assert np.all(np.diff(luma) <= 0.5) and luma[0] - luma[-1] > 150


def test_depth_picture_maps_near_to_far_along_the_lut_and_blanks_uncovered():
    depth = np.array([[0.5, 1.0, 1.5, 2.0, 3.0, 1.2]], np.float32)
    alpha = np.array([[1, 1, 1, 1, 1, COVERED / 2]], np.float32)
    out = depth_picture(depth, alpha, (1.0, 2.0))
    expected = [DEPTH_LUT[0], DEPTH_LUT[0], DEPTH_LUT[128], DEPTH_LUT[255], DEPTH_LUT[255], UNCOVERED]
    np.testing.assert_array_equal(out[0], np.array(expected, np.uint8))
    with pytest.raises(ValueError, match="^depth_range:"):
        depth_picture(depth, alpha, (2.0, 2.0))
    for bad in ((float("nan"), 1.0), (0.0, float("inf"))):
        with pytest.raises(ValueError, match="^depth_range:"):
            depth_picture(depth, alpha, bad)


@pytest.mark.parametrize("near_far", [(1e-300, 2e-300), (-1e300, 0.0), (-1e308, 1e308)])
def test_depth_picture_of_extreme_finite_ranges_is_a_picture(near_far):
    """Ranges whose float32 span is 0 or whose scale overflows still index the LUT (they once did not)."""
    depth = np.array([[0.0, 1e-300, 1.0, 3.0]], np.float32)
    out = depth_picture(depth, np.ones_like(depth), near_far)
    assert out.shape == (1, 4, 3) and out.dtype == np.uint8


def test_depth_range_is_the_percentiles_of_drawn_depths():
    depth = np.linspace(1.0, 2.0, 101, dtype=np.float32)[None]
    alpha = np.ones_like(depth)
    near, far = depth_range(depth, alpha)
    assert near == pytest.approx(1.02) and far == pytest.approx(1.98)
    assert depth_range(depth, np.zeros_like(depth)) == (0.0, 1.0)


def test_centre_depth_is_the_median_drawn_in_the_middle_ninth():
    depth = np.ones((9, 9), np.float32)
    depth[3:6, 3:6] = [[2, 2, 2], [3, 3, 3], [4, 4, 0]]  # one pixel there draws nothing
    alpha = np.ones_like(depth)
    assert centre_depth(depth, alpha) == 3.0
    alpha[3:6, 3:6] = 0
    assert centre_depth(depth, alpha) is None


def test_coverage_picture_runs_from_magenta_to_grey():
    out = coverage_picture(np.array([[0.0, 0.5, 1.0, 2.0]], np.float32))[0]
    np.testing.assert_array_equal(out[0], (200, 20, 140))
    np.testing.assert_array_equal(out[2], (225, 225, 225))
    np.testing.assert_array_equal(out[3], out[2])
    assert np.all(np.abs(out[1].astype(int) - (out[0].astype(int) + out[2]) / 2) <= 1)


def test_label_picture_uses_the_label_pngs_palette():
    labels = np.array([[-1, 0, 1], [7, 254, 2]])
    png = Image.open(io.BytesIO(wire.encode_label_png(labels))).convert("RGB")
    np.testing.assert_array_equal(label_picture(labels), np.asarray(png))
    np.testing.assert_array_equal(label_picture(np.array([[-1]]))[0, 0], PALETTE[0])
    assert visible_labels(labels) == [0, 1, 2, 7, 254]
    # past the palette's 255 labels: another label's colour, never the black of nothing drawn
    np.testing.assert_array_equal(label_picture(np.array([[255, 256]])), label_picture(np.array([[0, 1]])))


def test_camera_track_round_trip_drops_a_torn_row_and_frames_the_session_lacks(tmp_path):
    K = [[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]]
    c2w = np.eye(4)
    c2w[:3, 3] = (0.1, -0.2, 0.3)
    rows = [camera_row(k, Camera(K, c2w, 640, 480)) for k in range(3)]
    path = tmp_path / "cameras.f64"
    path.write_bytes(b"".join(r.tobytes() for r in rows) + b"\0" * 40)  # a torn last append
    track = read_track(path, frames=2)
    assert track.shape == (2, CAMERA_COLUMNS)
    first = camera_json(track[0])
    assert first == {"frame_index": 0, "width": 640, "height": 480, "K": [500.0, 510.0, 320.0, 240.0],
                     "c2w": [float(x) for x in c2w.ravel()]}
    assert read_track(tmp_path / "missing", frames=5).shape == (0, CAMERA_COLUMNS)
