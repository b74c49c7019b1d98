"""A frame's fold begun ahead (`Scene.prepare`, `folding.prepare`): the same bits as folding the frame,
made only where the scene's settings allow, made again where they changed."""

import dataclasses
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.scene import PreparedFrame, Scene

SYNTHETIC = list(synthetic_rgbd(num_frames=3, width=64, height=48))

VOXEL = 0.004


def reports_without_time(reports):
    return [dataclasses.replace(r, ms=0.0) for r in reports]


@pytest.mark.realdata
@pytest.mark.parametrize("undo_depth", [0, 4])
def test_frames_prepared_ahead_on_another_thread_fold_the_same_bits(shelf_frames, undo_depth):
    frames = shelf_frames[:12]
    plain = Scene(SceneConfig(voxel_size=VOXEL), undo_depth=undo_depth)
    expected = [plain.fold(f) for f in frames]
    scene = Scene(SceneConfig(voxel_size=VOXEL), undo_depth=undo_depth)
    reports = [scene.fold(frames[0])]  # the first frame chooses the settings left open (the sensor family)
    with ThreadPoolExecutor(max_workers=1) as ingest:  # three in flight, as a pipelined service holds them
        ahead = [ingest.submit(scene.prepare, f) for f in frames[1:4]]
        for k in range(1, len(frames)):
            prepared = ahead.pop(0).result()
            assert prepared.frame is frames[k] and prepared.config is not None and prepared.evidence is not None
            made = [prepared.evidence.points, prepared.evidence.features, prepared.basis, prepared.view.rgb]
            assert prepared.nbytes() > sum(a.nbytes for a in made)  # and rows, columns, colours, U_pos, R
            reports.append(scene.fold(prepared))
            if k + 3 < len(frames):
                ahead.append(ingest.submit(scene.prepare, frames[k + 3]))
    assert scene.digest() == plain.digest()
    assert reports_without_time(reports) == reports_without_time(expected)
    if undo_depth:  # undo records of prepared folds roll back as the plain ones do
        scene.rollback(9)
        plain.rollback(9)
        assert scene.digest() == plain.digest()


@pytest.mark.realdata
def test_a_frame_prepared_before_the_settings_are_chosen_is_folded_afresh(shelf_frames):
    scene, plain = Scene(SceneConfig(voxel_size=VOXEL)), Scene(SceneConfig(voxel_size=VOXEL))
    early = [scene.prepare(f) for f in shelf_frames[:3]]  # the first frame has not chosen the sensor family yet
    assert all(p.config is None and p.evidence is None and p.nbytes() == 0 for p in early)
    for p, f in zip(early, shelf_frames[:3]):
        scene.fold(p)
        plain.fold(f)
    assert scene.digest() == plain.digest()


@pytest.mark.realdata
def test_a_frame_prepared_under_other_settings_is_folded_afresh(shelf_frames):
    other = Scene(SceneConfig(voxel_size=2 * VOXEL))
    other.fold(shelf_frames[0])
    stale = other.prepare(shelf_frames[1])
    assert stale.evidence is not None
    scene, plain = Scene(SceneConfig(voxel_size=VOXEL)), Scene(SceneConfig(voxel_size=VOXEL))
    for target in (scene, plain):
        target.fold(shelf_frames[0])
    scene.fold(stale)  # made with a 8 mm scene's settings: its evidence is not used here
    plain.fold(shelf_frames[1])
    assert scene.digest() == plain.digest()


@pytest.mark.realdata
def test_a_learned_appearance_head_set_after_preparing_is_applied(shelf_frames):
    scene, plain = Scene(SceneConfig(voxel_size=VOXEL)), Scene(SceneConfig(voxel_size=VOXEL))
    for target in (scene, plain):
        target.fold(shelf_frames[0])
    prepared = scene.prepare(shelf_frames[1])
    assert prepared.evidence is not None
    with torch.no_grad():  # a head that weighs the evidence (U_app > 0 somewhere), the same in both scenes
        scene.appearance.mlp[2].weight.fill_(0.05)
        scene.appearance.mlp[2].bias.fill_(0.1)
    plain.appearance.load_state_dict(scene.appearance.state_dict())
    assert not scene.appearance.is_zero
    scene.fold(prepared)
    plain.fold(shelf_frames[1])
    assert scene.digest() == plain.digest()
    assert scene.prepare(shelf_frames[2]).evidence is None  # while the head weighs, nothing is made ahead


def test_nothing_is_made_for_frames_whose_fold_needs_the_scene():
    scene = Scene(SceneConfig(voxel_size=0.05))
    scene.fold(SYNTHETIC[0])
    assert scene.prepare(SYNTHETIC[1]).evidence is not None
    rgb_only = dataclasses.replace(SYNTHETIC[2], depth=None)
    unmade = scene.prepare(rgb_only)  # its depth is swept against the map's views
    assert unmade.frame is rgb_only and unmade[1:] == PreparedFrame(rgb_only)[1:]
    completing = Scene(SceneConfig(voxel_size=0.05, depth={"completion": True}))
    completing.fold(SYNTHETIC[0])
    assert completing.prepare(SYNTHETIC[1]).evidence is None  # holes are swept against the map


def test_a_frame_its_fold_refuses_is_refused_in_its_fold():
    scene = Scene(SceneConfig(voxel_size=0.05, features={"backend": "client", "dim": 8}))
    scene.fold(dataclasses.replace(SYNTHETIC[0], features=torch.zeros(48, 64, 8)))
    prepared = scene.prepare(SYNTHETIC[1])  # without client features
    assert prepared.frame is SYNTHETIC[1] and prepared[1:] == PreparedFrame(SYNTHETIC[1])[1:]
    digest = scene.digest()
    with pytest.raises(ValueError, match="^features: "):
        scene.fold(prepared)
    assert scene.digest() == digest


def test_prepare_names_a_wrong_argument():
    with pytest.raises(ValueError, match="^frame: expected a Frame, got dict"):
        Scene(SceneConfig(voxel_size=0.05)).prepare({})
