"""Label evidence: a pixel of no class (a class map's negative id, scores all 0) and a frame without
labels leave a voxel's label scores as they are, and a surface no labelled pixel saw renders no label."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from canonical_core import SceneConfig, render
from canonical_core.scene import Scene, aggregate_batch

from ..conftest import make_frame


def test_a_pixel_of_no_class_does_not_dilute_its_voxels_scores():
    """Two pixels in one voxel, class 1 and no class: the voxel's scores are class 1's alone, in the
    streaming fold and in the batch rule alike (before, the no-class pixel's weight went into the
    denominator and class 1 scored w0 / (w0 + w1))."""
    config = SceneConfig(voxel_size=1.0, sensor={"edge_weight": 0.0}, research={"weighting": "no_similarity"})
    scores = np.zeros((1, 2, 3), np.float32)
    scores[0, 0, 1] = 1.0  # the second pixel's row stays all 0: no class
    frame = make_frame(np.full((1, 2), 0.5), labels=scores, depth_std=[[0.1, 0.5]], fx=10.0)
    scene = Scene(config)
    scene.fold(frame)
    assert np.allclose(scene.fields()["labels"].numpy(), [[0.0, 1.0, 0.0]], rtol=0, atol=5e-4)
    assert np.allclose(aggregate_batch([frame], config)["labels"].numpy(), [[0.0, 1.0, 0.0]], rtol=0, atol=1e-6)


@pytest.mark.realdata
def test_surfaces_only_unlabelled_pixels_saw_render_no_label(shelf_frames):
    """The shelf's first frame with class 2 on its left half and no class (-1) on its right: rendered at
    that frame's own view, the left half reads 2 and the right half nothing (-1), where before every
    unlabelled surface read as class 0, the argmax of its all-zero scores. A frame without labels
    folded after adds no label either."""
    frame = shelf_frames[0]
    ids = np.full((frame.height, frame.width), -1, np.int16)
    ids[:, : frame.width // 2] = 2
    scene = Scene(SceneConfig(voxel_size=0.008))
    scene.fold(dataclasses.replace(frame, labels=ids, num_classes=3))
    scene.fold(shelf_frames[10])  # no labels: what only it sees stays unlabelled
    labels = render(scene.decode(), frame.camera, outputs=("labels", "alpha")).labels.numpy()
    half = frame.width // 2
    left, right = labels[:, : half - 8], labels[:, half + 8:]
    seen = frame.depth.numpy()[:, : half - 8] > 0  # frame 10 alone fills the first frame's depth holes
    assert (left[left >= 0] == 2).all() and (left[seen] == 2).mean() > 0.85
    assert (right == -1).mean() > 0.99
    assert not (labels == 0).any() and not (labels == 1).any()
