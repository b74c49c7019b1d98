"""Scene.update_poses / remove_frames: the corrected scene equals folding the corrected stream afresh."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from canonical_core import Scene, SceneConfig
from canonical_core.scene.corrections import FrameRef, check_poses, drift_walk, resolve_frames
from canonical_core.scene.corrections import drifted as drifted_frames
from tests.conftest import make_frame

CONFIG = SceneConfig(voxel_size=0.05, colour_solve={"views": 0})  # the fused state under test: its decodes too


def pose(tx: float, ty: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [tx, ty, 0.0]
    return T


def stream(n: int = 9, ids: bool = True) -> list:
    """``n`` small frames of a wavy wall at 1 m, the camera stepping sideways."""
    rng = np.random.default_rng(1)
    frames = []
    for k in range(n):
        depth = 1.0 + 0.05 * np.sin(np.arange(24)[None, :] / 3.0 + k) + np.zeros((20, 24))
        rgb = rng.integers(0, 255, (20, 24, 3))
        frame = make_frame(depth, rgb=rgb, fx=20.0, c2w=pose(0.04 * k, yaw=0.02 * k))
        frames.append(replace(frame, frame_id=f"f{k}") if ids else frame)
    return frames


def fold(frames, keep: bool = False) -> Scene:
    scene = Scene(CONFIG, keep_frames=keep)
    for frame in frames:
        scene.fold(frame)
    return scene


def drifted(frames, seed: int = 0) -> list:
    """The frames with a random walk (1 cm, 0.5 degrees per frame) added to their poses."""
    return drifted_frames(frames, drift_walk(len(frames), 0.01, 0.5, seed=seed))


def test_update_poses_equals_folding_the_corrected_stream():
    clean = stream()
    scene = fold(drifted(clean), keep=True)
    assert scene.digest() != fold(clean).digest()  # the drift changed the scene
    scene.update_poses({f.frame_id: f.camera.c2w64() for f in clean})
    assert scene.digest() == fold(clean).digest()
    assert [r.frame_id for r in scene.frame_refs()] == [f.frame_id for f in clean]


def test_partial_correction_by_arrival_index():
    clean = stream(ids=False)
    bad = drifted(clean)
    scene = fold(bad, keep=True)
    fixed = {3: clean[3].camera.c2w64(), "5": clean[5].camera.c2w64()}  # an int and a decimal string
    scene.update_poses(fixed)
    expected = [clean[k] if k in (3, 5) else f for k, f in enumerate(bad)]
    assert scene.digest() == fold(expected).digest()


def test_remove_a_random_third_equals_fusing_the_rest():
    frames = stream(12)
    rng = np.random.default_rng(3)
    gone = sorted(rng.choice(12, 4, replace=False).tolist())
    scene = fold(frames, keep=True)
    scene.remove_frames([f"f{k}" for k in gone])
    kept = [f for k, f in enumerate(frames) if k not in gone]
    assert scene.digest() == fold(kept).digest()
    # the others keep their arrival indices, so a later correction by index still names the same frame
    assert [r.arrival for r in scene.frame_refs()] == [k for k in range(12) if k not in gone]
    survivor = next(k for k in range(12) if k not in gone and k > gone[0])
    scene.update_poses({survivor: pose(0.5)})
    kept = [replace(f, camera=f.camera.with_pose(pose(0.5))) if f.frame_id == f"f{survivor}" else f for f in kept]
    assert scene.digest() == fold(kept).digest()


def test_removing_every_frame_that_saw_a_region_empties_it():
    near = [make_frame(np.full((10, 12), 1.0), fx=10.0, c2w=pose(0.02 * k)) for k in range(3)]
    far = [make_frame(np.full((10, 12), 1.0), fx=10.0, c2w=pose(5.0 + 0.02 * k)) for k in range(3)]
    scene = fold([near[0], far[0], near[1], far[1], near[2], far[2]], keep=True)
    assert (scene.fields()["representative_position"][:, 0] > 4.0).any()  # world x of each voxel's representative
    scene.remove_frames([1, 3, 5])
    assert len(scene) and not (scene.fields()["representative_position"][:, 0] > 4.0).any()
    assert scene.digest() == fold(near).digest()


def test_drift_walk_steps_by_the_given_size():
    walk = drift_walk(25, 0.01, 0.5, every=10, seed=4)
    assert np.array_equal(walk[0], walk[9]) and not np.array_equal(walk[9], walk[10])  # a step every 10 frames
    steps = [np.linalg.inv(walk[k - 10]) @ walk[k] for k in (10, 20)]
    for step in steps:  # each step: 1 cm and 0.5 degrees (the rotation's angle), a rigid motion
        assert np.linalg.det(step[:3, :3]) == pytest.approx(1.0)
        angle = np.degrees(np.arccos((np.trace(step[:3, :3]) - 1) / 2))
        assert angle == pytest.approx(0.5, abs=1e-6)
    first = walk[0][:3, 3]
    assert np.linalg.norm(first) == pytest.approx(0.01)


def test_removing_every_frame_leaves_an_empty_scene():
    scene = fold(stream(3), keep=True)
    scene.remove_frames(["f0", "f1", "f2"])
    assert len(scene) == 0 and scene.frames == 0 and scene.digest() == Scene(CONFIG).digest()


def test_a_corrected_scene_folds_on_like_the_fresh_one():
    frames = stream(8)
    scene = fold(drifted(frames[:6]), keep=True)
    scene.update_poses({f.frame_id: f.camera.c2w64() for f in frames[:6]})
    for frame in frames[6:]:
        scene.fold(frame)
    assert scene.digest() == fold(frames).digest()
    assert scene.gaussians().means.shape == fold(frames).gaussians().means.shape


@pytest.mark.parametrize("poses, field", [
    ({"nope": np.eye(4)}, "poses.nope"),
    ({99: np.eye(4)}, "poses.99"),
    ({"f1": np.full((4, 4), np.nan)}, "poses.f1"),
    ({"f1": np.diag([2.0, 1.0, 1.0, 1.0])}, "poses.f1"),  # not rigid
    ({"f1": np.eye(3)}, "poses.f1"),
    ({"f1": np.eye(4), 1: np.eye(4)}, "poses.1"),  # the same frame twice
    ({}, "poses"),
])
def test_bad_corrections_name_the_field_and_change_nothing(poses, field):
    scene = fold(stream(4), keep=True)
    before = scene.digest()
    with pytest.raises(ValueError, match=rf"^{field}[:.]"):
        scene.update_poses(poses)
    assert scene.digest() == before


def test_bad_removals_and_scenes_without_frames():
    scene = fold(stream(3), keep=True)
    before = scene.digest()
    with pytest.raises(ValueError, match=r"^frames\.f9: "):
        scene.remove_frames(["f0", "f9"])
    with pytest.raises(ValueError, match=r"^frames: expected a list"):
        scene.remove_frames("f0")
    for nothing in ([], set()):
        with pytest.raises(ValueError, match=r"^frames: names no frame$"):
            scene.remove_frames(nothing)
    assert scene.digest() == before
    plain = fold(stream(2))
    with pytest.raises(ValueError, match=r"^poses: this scene keeps no frames"):
        plain.update_poses({"f0": np.eye(4)})
    with pytest.raises(ValueError, match=r"^frames: this scene keeps no frames"):
        plain.remove_frames(["f0"])


def test_keys_prefer_a_frame_id_over_an_arrival_index():
    refs = [FrameRef(0, "1"), FrameRef(1, None), FrameRef(2, None)]
    assert resolve_frames(["1", 2], refs, "frames") == [0, 2]  # "1" is frame 0's id, not arrival 1
    assert resolve_frames([1], refs, "frames") == [1]  # an int is always an arrival index
    assert list(check_poses({"2": np.eye(4)}, refs)) == [2]
    with pytest.raises(ValueError, match=r"^frames: frame keys"):
        resolve_frames([1.0], refs, "frames")


def test_a_frame_id_two_kept_frames_share_names_neither():
    """A library's frames may share an id (a capture listing one image twice): the key is refused,
    naming the arrival indices that tell them apart, instead of the last one taken silently."""
    refs = [FrameRef(0, "same"), FrameRef(1, "same"), FrameRef(2, "other")]
    with pytest.raises(ValueError, match=r"^frames\.same: names 2 kept frames \(arrival indices \[0, 1\]\)"):
        resolve_frames(["same"], refs, "frames")
    assert resolve_frames([1, "other"], refs, "frames") == [1, 2]


def test_a_key_of_thousands_of_digits_names_no_frame():
    """Such a key once reached int() and CPython's digit limit: an error that named no field."""
    refs = [FrameRef(0, None)]
    key = "0" * 4301 + "1"
    with pytest.raises(ValueError, match=r"^frames\.0{4301}1: no kept frame") as err:
        resolve_frames([key], refs, "frames")
    assert err.value.field == f"frames.{key}"
    assert resolve_frames(["0" * 19], refs, "frames") == [0]  # leading zeros within an int64's digits still count


@pytest.mark.parametrize("undo_depth", [0, 3])  # 3: the last frames roll back in place, earlier ones use checkpoints
@pytest.mark.parametrize("touch", [0, 4, 5, 9, 11])  # before, at and after the checkpoints (every 5 frames)
def test_refolding_from_a_checkpoint_equals_refolding_all(touch, undo_depth):
    frames = stream(12)
    bad = drifted(frames)
    scene = Scene(CONFIG, keep_frames=True, checkpoint_every=5, undo_depth=undo_depth)
    for frame in bad:
        scene.fold(frame)
    assert sorted(scene._checkpoints) == [5, 10]
    scene.update_poses({f"f{k}": frames[k].camera.c2w64() for k in range(touch, 12)})
    assert scene.digest() == fold(bad[:touch] + frames[touch:]).digest()
    assert sorted(scene._checkpoints) == [5, 10]
    scene.remove_frames([f"f{touch}"])
    rest = [f for k, f in enumerate(bad[:touch] + frames[touch:]) if k != touch]
    assert scene.digest() == fold(rest).digest()
    assert sorted(scene._checkpoints) == [5, 10]  # taken again at the new positions


def test_a_correction_after_a_checkpoint_does_not_refold_the_frames_before_it():
    frames = stream(12)
    scene = Scene(CONFIG, keep_frames=True, checkpoint_every=5, undo_depth=0)
    for frame in frames:
        scene.fold(frame)
    scene._kept[0] = drifted(frames)[0]  # were frame 0 re-folded, the digest would show it
    scene.update_poses({"f11": frames[11].camera.c2w64()})
    assert scene.digest() == fold(frames).digest()
    scene.update_poses({"f3": frames[3].camera.c2w64()})  # before the first checkpoint: all re-folded
    assert scene.digest() == fold(drifted(frames)[:1] + frames[1:]).digest()


def test_checkpoint_every_is_checked():
    with pytest.raises(ValueError, match=r"^checkpoint_every: "):
        Scene(CONFIG, keep_frames=True, checkpoint_every=-1)
