"""Undo records: a scene rolls back its last folds exactly, and a correction of recent frames re-folds only them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from canonical_core import Frame, Scene, SceneConfig
from canonical_core.datasets import load_dataset
from canonical_core.scene.free_space import CHUNK
from canonical_core.scene.undo import MIN_KEPT, FoldUndo, FreeBefore, UndoRing
from tests.conftest import DATA
from tests.scene.test_corrections import CONFIG, drifted, fold, pose, stream


def mixed_stream(n: int = 10) -> list[Frame]:
    """`stream` with frames 0 and 4 without depth: 0 waits for a partner (pending) until 4 arrives."""
    frames = stream(n)
    for k in (0, 4):
        frames[k] = Frame(rgb=frames[k].rgb, camera=frames[k].camera, frame_id=frames[k].frame_id)
    return frames


def state(scene: Scene) -> dict[str, np.ndarray]:
    return {k: v.copy() for k, v in scene._snapshot_arrays().items()}


def assert_same_gaussians(a, b) -> None:
    for name in ("means", "scales", "quats", "opacities", "sh", "features"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("back_to", [0, 3, 5, 9])
def test_rollback_restores_every_array_and_folding_on_gives_the_same_scene(back_to):
    frames = mixed_stream()
    scene = Scene(CONFIG, undo_depth=len(frames))
    digests, states = [scene.digest()], [state(scene)]
    for frame in frames:
        scene.fold(frame)
        digests.append(scene.digest())
        states.append(state(scene))
    scene.decode()
    scene.rollback(back_to)
    assert scene.frames == back_to and scene.digest() == digests[back_to]
    assert_same_gaussians(scene.decode(), fold(frames[:back_to]).decode())
    after = state(scene)
    assert sorted(after) == sorted(states[back_to])
    for name, array in states[back_to].items():
        np.testing.assert_array_equal(after[name], array, err_msg=name)
    for frame in frames[back_to:]:
        scene.fold(frame)
    assert scene.digest() == digests[-1]


@pytest.mark.realdata
def test_a_room_scale_walk_rolls_back_exactly_and_its_records_keep_the_frustums_chunks_only():
    """Many chunks, most outside each frame's view, the last one partly filled: what the small
    stream above never reaches."""
    if not (DATA / "hololens_office").is_dir():
        pytest.skip("real capture not found")
    frames = list(load_dataset(DATA / "hololens_office", stride=8, max_frames=12))
    scene = Scene(SceneConfig(voxel_size=0.02, colour_solve={"views": 0}), undo_depth=4)
    for frame in frames[:8]:
        scene.fold(frame)
    digest, expected = scene.digest(), state(scene)
    for frame in frames[8:]:
        scene.fold(frame)
    scene.decode()  # decoded rows kept: those the roll-back leaves alone are reused by the next decode
    chunks = -(-len(scene._voxels) // CHUNK)
    kept = [len(b.chunks) for r in scene._undo.records for b in r.before if isinstance(b, FreeBefore)]
    assert len(kept) == 4 and 0 < max(kept) < chunks
    scene.rollback(8)
    assert scene.digest() == digest
    after = state(scene)
    for name, array in expected.items():
        np.testing.assert_array_equal(after[name], array, err_msg=name)
    table = scene._voxels.table.copy()  # the created voxels left the table: as a rebuild would leave it
    scene._voxels.rebuild_table()
    np.testing.assert_array_equal(table, scene._voxels.table)
    fresh = Scene(SceneConfig(voxel_size=0.02, colour_solve={"views": 0}))
    for frame in frames[:8]:
        fresh.fold(frame)
    assert_same_gaussians(scene.decode(), fresh.decode())


def test_free_before_keeps_the_chunks_below_the_limit_and_puts_them_back():
    rng = np.random.default_rng(0)
    free = rng.random(5 * CHUNK + 300, dtype=np.float32)
    original, limit = free.copy(), 4 * CHUNK + 100  # chunk 4 holds 100 voxels older than the pass
    before = FreeBefore.of(free, np.array([0, 2, 4, 5], np.int32), limit)
    assert before.chunks.tolist() == [0, 2, 4] and before.values.shape == (2 * CHUNK + 100,)
    free += 1.0
    before.restore(type("Voxels", (), {"state": {"free": free}})())
    kept = np.zeros(free.shape, bool)
    for c in (0, 2):
        kept[c * CHUNK: (c + 1) * CHUNK] = True
    kept[4 * CHUNK: limit] = True
    np.testing.assert_array_equal(free[kept], original[kept])
    np.testing.assert_array_equal(free[~kept], original[~kept] + 1.0)


def test_rollback_reaches_back_undo_depth_folds_only():
    frames = stream(8)
    scene = Scene(CONFIG, undo_depth=3)
    for frame in frames:
        scene.fold(frame)
    assert scene.undo_floor == 5 and scene.undo_bytes() > 0 and Scene(CONFIG).undo_bytes() == 0
    with pytest.raises(ValueError, match=r"^frames: the undo records reach back to 5 frames"):
        scene.rollback(4)
    assert scene.digest() == fold(frames).digest()  # refused: nothing changed
    with pytest.raises(ValueError, match=r"^frames: expected a frame count"):
        scene.rollback(9)
    with pytest.raises(ValueError, match=r"^undo_depth: "):
        Scene(CONFIG, undo_depth=-1)
    assert Scene(CONFIG).undo_floor == 0 and Scene(CONFIG, keep_frames=True)._undo.depth > 0


def test_a_correction_of_recent_frames_refolds_only_them():
    frames = stream(12)
    scene = Scene(CONFIG, keep_frames=True, undo_depth=4)
    for frame in frames:
        scene.fold(frame)
    scene._kept[7] = drifted(frames)[7]  # were frame 7 re-folded, the digest would show it
    scene.update_poses({"f10": frames[10].camera.c2w64(), "f11": pose(0.5)})
    moved = replace(frames[11], camera=frames[11].camera.with_pose(pose(0.5)))
    assert scene.digest() == fold(frames[:11] + [moved]).digest()
    scene.remove_frames(["f9"])  # the re-fold left records for the frames it folded: in place again
    assert scene.digest() == fold(frames[:9] + frames[10:11] + [moved]).digest()
    assert scene.undo_floor == 8  # the last 4 folds: 8, 9 (kept) and the two the removal re-folded


def test_by_default_a_correction_of_the_last_five_frames_refolds_only_them():
    frames = stream(12)
    scene = Scene(CONFIG, keep_frames=True)
    for frame in frames:
        scene.fold(frame)
    scene._kept[6] = drifted(frames)[6]  # were frame 6 re-folded, the digest would show it
    moved = replace(frames[7], camera=frames[7].camera.with_pose(pose(0.5)))
    scene.update_poses({"f7": pose(0.5)} | {f"f{k}": frames[k].camera.c2w64() for k in range(8, 12)})
    assert scene.digest() == fold(frames[:7] + [moved] + frames[8:]).digest()


def test_labels_that_widen_the_rows_end_the_records_before_them():
    frames = stream(6)
    labels = np.zeros((20, 24, 2), np.float32)
    labels[..., 1] = 1.0
    frames[3] = replace(frames[3], labels=__import__("torch").from_numpy(labels))
    scene = Scene(CONFIG, keep_frames=True, undo_depth=8)
    for frame in frames:
        scene.fold(frame)
    assert scene.undo_floor == 4  # the fold that widened the rows cannot be undone; those after it can
    scene.update_poses({"f5": pose(0.3)})
    moved = replace(frames[5], camera=frames[5].camera.with_pose(pose(0.3)))
    assert scene.digest() == fold(frames[:5] + [moved]).digest()
    scene.update_poses({"f1": pose(0.3)})  # before the records: a re-fold from the start
    first = replace(frames[1], camera=frames[1].camera.with_pose(pose(0.3)))
    assert scene.digest() == fold(frames[:1] + [first] + frames[2:5] + [moved]).digest()


def test_a_correction_that_fails_in_place_leaves_the_scene_as_it_was():
    frames = stream(6)
    full = fold(frames)
    scene = Scene(SceneConfig(voxel_size=CONFIG.voxel_size, max_voxels=len(full) + 5, colour_solve={"views": 0}), keep_frames=True)
    for frame in frames:
        scene.fold(frame)
    before = scene.digest()
    with pytest.raises(ValueError, match=r"^max_voxels: "):
        scene.update_poses({"f4": pose(3.0), "f5": pose(6.0)})  # new ground: past the cap
    assert scene.digest() == before and scene.frames == 6
    assert [r.frame_id for r in scene.frame_refs()] == [f.frame_id for f in frames]
    scene.update_poses({"f5": frames[5].camera.c2w64()})  # the records still serve
    assert scene.digest() == before


def test_the_ring_keeps_the_last_records_only():
    ring = UndoRing(depth=2)
    assert ring.floor(7) == 7 and ring.take(7, 7) == []
    with pytest.raises(ValueError, match=r"^frames: the undo records reach back to 7 frames, not 3"):
        ring.take(3, 7)
    for frames in (7, 8, 9):
        ring.push(FoldUndo(frames, 0, 0, [], [], ([], []), (0.0, 0)), map_bytes=0)  # no share: the depth alone
    assert len(ring) == 2 and ring.floor(10) == 8
    assert [r.frames for r in ring.take(9, 10)] == [9] and ring.floor(9) == 8


def test_a_share_of_the_maps_bytes_bounds_the_records_past_the_newest_few():
    ring = UndoRing(depth=8, max_share=0.5)
    record = FoldUndo(0, 0, 0, [], [], ([], []), (0.0, 0), before=[FreeBefore(np.zeros(0, np.int32), 0,
                                                                          np.zeros(100, np.float32))])
    for frames in range(8):
        ring.push(replace(record, frames=frames), map_bytes=100)  # 400 bytes each, past any share of 100
    assert len(ring) == MIN_KEPT and ring.nbytes() == 400 * MIN_KEPT and ring.floor(8) == 8 - MIN_KEPT
    for frames in range(8, 16):
        ring.push(replace(record, frames=frames), map_bytes=5600)  # 2800 bytes: 7 records
    assert len(ring) == 7 and ring.nbytes() == 2800 and ring.floor(16) == 9
    ring.push(replace(record, frames=16), map_bytes=10_000)  # the depth: 8 at most
    assert len(ring) == 8 and ring.floor(17) == 9
    assert [r.frames for r in ring.take(15, 17)] == [16, 15] and ring.nbytes() == 2400
    with pytest.raises(ValueError, match=r"^max_share: "):
        Scene(CONFIG).keep_undo(4, max_share=0.0)


@pytest.mark.realdata
def test_a_bounded_ring_keeps_within_its_share_and_rolls_back_exactly(shelf_frames):
    config = SceneConfig(voxel_size=0.01)
    scene = Scene(config)
    scene.keep_undo(32, max_share=0.5)
    digests = []
    for frame in shelf_frames[:8]:
        scene.fold(frame)
        digests.append(scene.digest())
        assert 0 < scene.undo_bytes() <= 0.5 * scene._voxels.nbytes() or len(scene._undo) <= MIN_KEPT
    floor = scene.undo_floor
    assert floor == 8 - MIN_KEPT  # the share, not the depth (32), dropped the older records
    scene.rollback(floor)
    assert scene.digest() == digests[floor - 1]


def test_refold_after_is_a_rollback_and_folds_in_one_step():
    """`Scene.refold_after` gives the scene a rollback and the folds give (the service's correction of
    recent frames takes it, so that no reader sees the state between); a bad count names ``first``."""
    frames = stream(8)
    a, b = Scene(CONFIG, undo_depth=8), Scene(CONFIG, undo_depth=8)
    for f in frames:
        a.fold(f)
        b.fold(f)
    shift = torch.as_tensor(pose(0.02), dtype=frames[0].camera.c2w.dtype)
    moved = [replace(f, camera=replace(f.camera, c2w=shift @ f.camera.c2w)) for f in frames[5:]]
    a.refold_after(5, moved)
    b.rollback(5)
    for f in moved:
        b.fold(f)
    assert a.digest() == b.digest() and a.frames == 8
    for first in (-1, 9, True, 2.0):
        with pytest.raises(ValueError, match="^first: "):
            a.refold_after(first, [])
    assert a.digest() == b.digest()
