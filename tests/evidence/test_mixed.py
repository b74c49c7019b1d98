"""Mixed ("flying") depth pixels: the two rules on a known edge, and extraction without them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.evidence import extract_evidence
from canonical_core.evidence.mixed import mixed_pixels


def _edge_depth() -> np.ndarray:  # [24, 32]: 1 m left of column 15, 2 m right of 16, column 15 blended at 1.5 m
    depth = np.full((24, 32), 1.0, np.float32)
    depth[:, 16:] = 2.0
    depth[:, 15] = 1.5
    depth[5, 5] = 1.02  # a 2 % bump: noise, no edge
    return depth


def test_the_jump_rule_drops_both_sides_and_the_between_rule_only_the_blend():
    depth = _edge_depth()
    rows, cols = np.nonzero(depth > 0)
    jump = mixed_pixels(depth, rows, cols, 0.05, "jump")
    between = mixed_pixels(depth, rows, cols, 0.05, "between")
    assert set(cols[jump].tolist()) == {14, 15, 16}
    assert set(cols[between].tolist()) == {15}
    assert jump.sum() == 3 * 24 and between.sum() == 24
    assert not mixed_pixels(depth, rows, cols, 0.6, "jump").any()  # 1.5 -> 2.0 is a 33 % jump
    with pytest.raises(ValueError, match="rule"):
        mixed_pixels(depth, rows, cols, 0.05, "nearest")
    with pytest.raises(ValueError, match="threshold"):
        mixed_pixels(depth, rows, cols, 0.0)


def test_extraction_leaves_mixed_pixels_out_only_when_asked():
    depth = _edge_depth()
    camera = Camera([[30.0, 0, 16.0], [0, 30.0, 12.0], [0, 0, 1]], np.eye(4), 32, 24)
    frame = Frame(rgb=torch.zeros((24, 32, 3), dtype=torch.uint8), camera=camera, depth=torch.from_numpy(depth))
    every = extract_evidence(frame, SceneConfig(voxel_size=0.02))
    assert len(every) == 24 * 32
    kept = extract_evidence(frame, SceneConfig(voxel_size=0.02, sensor={"mixed_jump": 0.05, "mixed_rule": "between"}))
    assert len(kept) == 24 * 31 and not (kept.cols == 15).any()
    # the rest of the evidence is the same, row for row
    same = every.cols != 15
    np.testing.assert_array_equal(kept.points, every.points[same])
    np.testing.assert_array_equal(kept.reliability, every.reliability[same])
    with pytest.raises(ValueError, match="sensor.mixed_jump"):
        SceneConfig(voxel_size=0.02, sensor={"mixed_jump": -0.1})
