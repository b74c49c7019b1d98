"""label-fusion's bins: bit-rotated depth in tenths of a millimetre (poses held by a depth warp), label
maps read as one-hot labels with the capture's ids, detection, and what a malformed bin says."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from PIL import Image

from canonical_core.datasets import SkippedFrames, load_dataset, load_label_fusion
from canonical_core.datasets.detect import detect_layout
from canonical_core.datasets.label_fusion import unrotate_depth


def test_depth_is_unrotated_and_read_in_tenths_of_a_millimetre():
    d = np.array([[0, 4100, 65535 >> 1]], np.uint32)  # 0 (missing), 0.41 m, a large value
    stored = (((d << 3) | (d >> 13)) & 0xFFFF).astype(np.uint16)  # the capture's rotation
    assert unrotate_depth(stored).tolist() == d.tolist()


@pytest.mark.parametrize("folder, ids", [("bin_labels", (0, 48, 132)), ("bin_mask", (0, 255))])
def test_a_bin_loads_with_depth_that_warps_onto_the_next_frame_and_labels_as_labels(apc_bins_path, reprojection_error,
                                                                                     folder, ids):
    seq = load_label_fusion(apc_bins_path / folder)
    assert len(seq) == 15 and seq.label_ids == ids and detect_layout(apc_bins_path / folder) == "label_fusion"
    a, b = seq[5], seq[6]
    assert 0.2 < float(a.depth[a.depth > 0].median()) < 1.0  # a bin seen from about 0.4-0.6 m
    error, compared = reprojection_error(a, b)
    assert compared > 10_000 and error < 0.02  # the capture's README: 5-8 mm
    labels = a.labels.numpy()  # a class map: one class a pixel, every pixel one of the capture's ids
    assert labels.shape == (480, 640) and a.num_classes == a.label_dim == len(ids)
    assert set(np.unique(labels)) == set(range(len(ids)))
    suffix = "segm" if folder == "bin_labels" else "mask"
    stored = np.asarray(Image.open(apc_bins_path / folder / f"frame-000005.{suffix}.png"))
    assert (np.array(ids)[labels] == stored).all()  # class c is id ids[c]


def test_every_frame_has_the_captures_label_channels_whatever_the_stride(apc_bins_path):
    seq = load_dataset(apc_bins_path / "bin_labels", stride=7)
    assert seq.frame_ids == ["frame-000000", "frame-000007", "frame-000014"]
    assert {f.label_dim for f in seq} == {3}


def test_a_malformed_bin_names_the_file(apc_bins_path, tmp_path):
    bin_ = tmp_path / "bin"
    shutil.copytree(apc_bins_path / "bin_labels", bin_)
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(bin_ / "frame-000003.segm.png")
    with pytest.raises(ValueError, match=r"frame-000003\.segm\.png: label map 10x10 does not match"):
        load_label_fusion(bin_)[3]
    (bin_ / "frame-000004.depth.png").unlink()
    with pytest.raises(ValueError, match=r"frame-000004\.depth\.png: file not found"):
        load_label_fusion(bin_, strict=True)
    with pytest.warns(SkippedFrames, match="skipped 1 of 15 listed frames"):
        assert "frame-000004" not in load_label_fusion(bin_).frame_ids
    (bin_ / "camera-intrinsics.color.txt").unlink()
    with pytest.raises(ValueError, match="no intrinsics file"):
        load_label_fusion(bin_)
    for p in bin_.glob("frame-*.segm.png"):
        p.unlink()
    with pytest.raises(ValueError, match="not a label-fusion folder"):
        load_label_fusion(bin_)


def test_a_tsdf_fusion_capture_with_masks_beside_its_frames_keeps_its_millimetres(tmp_path):
    """Label maps added to a tsdf-fusion capture make it a label-fusion folder; its depth is still
    millimetres, not label-fusion's bit-rotated code (the decoding that is a surface wins)."""
    from canonical_core.datasets import load_tsdf_fusion, synthetic_rgbd, write_tsdf_fusion

    root = write_tsdf_fusion(synthetic_rgbd(num_frames=3, width=64, height=48), tmp_path / "cap")
    plain = load_tsdf_fusion(root)
    for color in root.rglob("frame-*.color.png"):
        Image.fromarray(np.full((48, 64), 255, np.uint8)).save(color.with_name(color.name.replace(".color.", ".mask.")))
    assert detect_layout(root) == "label_fusion"
    masked = load_label_fusion(root)
    assert np.array_equal(masked[1].depth.numpy(), plain[1].depth.numpy()) and masked[1].num_classes == 1
