"""Pose corrections on real captures: a drifted stream loses held-out quality, and one correction
with the true poses gives back the clean fusion exactly (digest, hence every figure)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest

from canonical_core import Scene, SceneConfig
from canonical_core.datasets import load_dataset
from canonical_core.eval.methods import SplatModel
from canonical_core.eval.run import score
from canonical_core.frame import resize_frame
from canonical_core.scene.corrections import drift_walk, drifted
from tests.conftest import DATA

pytestmark = pytest.mark.realdata

# (capture, image scale, stride, frames, voxel size, every k-th frame held out): reduced so each runs in seconds
CAPTURES = {"realsense_shelf": (0.25, 2, 25, 0.01, 8), "hololens_office": (0.25, 3, 60, 0.04, 20)}


def capture(name: str):
    if not (DATA / name).is_dir():
        pytest.skip(f"real capture not found at {DATA / name}")
    return _capture(name)


@lru_cache(maxsize=None)
def _capture(name: str):
    scale, stride, count, voxel, every = CAPTURES[name]
    frames = [resize_frame(f, scale) for f in load_dataset(DATA / name, stride=stride, max_frames=count)]
    held = list(range(3, len(frames), every))
    return frames, [k for k in range(len(frames)) if k not in held], held, voxel


def fused(frames, positions, voxel: float) -> Scene:
    # the colour solve off: it would fit colours to the drifted views too, and the subject is the fusion
    scene = Scene(SceneConfig(voxel_size=voxel, colour_solve={"views": 0}), keep_frames=True)
    for k in positions:
        scene.fold(frames[k])
    return scene


def figures(scene: Scene, targets, voxel: float) -> dict:
    m = score(SplatModel(scene.gaussians()), targets, voxel).metrics
    return {k: m[k] for k in ("psnr", "psnr_covered", "depth_agreement")}


@pytest.mark.parametrize("name", list(CAPTURES))
def test_drift_then_one_correction_gives_back_the_clean_fusion(name):
    frames, inputs, held, voxel = capture(name)
    targets = [frames[k] for k in held]
    clean = fused(frames, inputs, voxel)
    expected = figures(clean, targets, voxel)
    walk = drift_walk(len(frames), 0.01, 0.5, every=10, seed=0)  # 1 cm and 0.5 degrees per 10 frames
    scene = fused(drifted(frames, walk), inputs, voxel)
    drift = figures(scene, targets, voxel)
    assert drift["psnr"] < expected["psnr"] - 0.1
    assert drift["psnr_covered"] < expected["psnr_covered"] and drift["depth_agreement"] < expected["depth_agreement"]
    scene.update_poses({frames[k].frame_id: frames[k].camera.c2w64() for k in inputs})  # one correction
    assert scene.digest() == clean.digest()
    back = figures(scene, targets, voxel)
    for key in ("psnr", "psnr_covered"):
        assert abs(back[key] - expected[key]) <= 0.05
    assert back["depth_agreement"] == expected["depth_agreement"]


def test_removing_a_random_third_of_a_real_stream_equals_fusing_the_rest():
    frames, inputs, _, voxel = capture("realsense_shelf")
    rng = np.random.default_rng(11)
    gone = set(rng.choice(inputs, len(inputs) // 3, replace=False).tolist())
    scene = fused(frames, inputs, voxel)
    scene.remove_frames([frames[k].frame_id for k in sorted(gone)])
    assert scene.digest() == fused(frames, [k for k in inputs if k not in gone], voxel).digest()
