"""Settings a scene leaves to its first frame (`scene.choices`): the voxel size by the evaluation's rule,
the sensor family from the depth's quantisation, their presets under explicit values, and that the
choice is made once, survives snapshots and corrections, and is refused without depth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.config import DEFAULT_FAMILY, SENSOR_PRESETS, detect_family, disparity_step
from canonical_core.datasets import load_dataset
from canonical_core.eval import run
from canonical_core.scene.choices import choose_settings, default_voxel_size, filled_from
from tests.conftest import DATA, require_capture

pytestmark = pytest.mark.realdata

CAPTURES = {  # capture -> (family, how it is chosen)
    "sun3d_studyroom": ("structured_light", "detected from depth quantisation"),
    "realsense_shelf": (DEFAULT_FAMILY, "default: "),
    "hololens_office": (DEFAULT_FAMILY, "default: "),
    "apc_bins/bin_labels": (DEFAULT_FAMILY, "default: "),
    "livingroom_synthetic": (DEFAULT_FAMILY, "default: "),
}


@pytest.fixture(scope="module")
def first_frames() -> dict:
    return {name: load_dataset(require_capture(DATA / name), max_frames=1)[0] for name in CAPTURES}


@pytest.fixture(scope="module")
def shelf(shelf_dir) -> list:
    return list(load_dataset(shelf_dir, stride=10, max_frames=4))


def test_the_evaluation_uses_the_librarys_voxel_rule():
    assert run.default_voxel_size is default_voxel_size


def test_the_voxel_rule_is_six_pixel_footprints_at_the_median_depth(first_frames):
    frame = first_frames["realsense_shelf"]
    depth = frame.depth.numpy()
    footprint = float(np.median(depth[depth > 0])) / ((frame.camera.fx + frame.camera.fy) / 2)
    assert default_voxel_size([frame]) == float(f"{6 * footprint:.2g}")
    with pytest.raises(ValueError, match="^voxel_size: no valid depth"):
        default_voxel_size([dataclasses.replace(frame, depth=None)])


@pytest.mark.parametrize("name", sorted(CAPTURES))
def test_each_capture_gets_its_family_from_its_first_frame(first_frames, name):
    family, why = detect_family(first_frames[name].depth)
    assert family == CAPTURES[name][0] and why.startswith(CAPTURES[name][1])


def test_structured_light_steps_are_the_kinect_disparity_step(first_frames):
    # Kinect v1: 1/8 pixel of disparity at f B of about 43 px m is a step of about 2.9e-3 z^2
    assert disparity_step(first_frames["sun3d_studyroom"].depth) == pytest.approx(2.9e-3, rel=0.05)
    # depth in whole millimetres from a sensor without coarser steps shows none
    assert disparity_step(first_frames["hololens_office"].depth) is None


def test_synthetic_disparity_quantisation_is_told_by_its_step():
    z = np.linspace(0.8, 3.0, 20_000).reshape(100, 200)
    for c, family in ((2.9e-3, "structured_light"), (1.2e-3, "active_stereo")):
        disparity = np.round(1.0 / (c * z))  # depth from a disparity in whole steps: levels c z^2 apart
        assert detect_family(1.0 / (c * disparity))[0] == family
    assert detect_family(z + 1e-3 * np.random.default_rng(0).standard_normal(z.shape))[1].startswith("default")
    assert detect_family(np.full((8, 8), 1.5))[1].startswith("default")  # too little range to tell
    assert detect_family(None) == (DEFAULT_FAMILY, "default: no depth to detect it from")


def test_explicit_values_win_over_the_family_and_the_family_over_detection(first_frames):
    frame = first_frames["sun3d_studyroom"]  # detected as structured light
    config, why = choose_settings(SceneConfig(sensor={"family": "hololens", "sigma0": 0.004}), frame)
    floor = {"weight_floor": SceneConfig().sensor.weight_floor}  # not a noise value: no preset sets it
    assert config.sensor.model_dump() == {**SENSOR_PRESETS["hololens"], "sigma0": 0.004, "family": "hololens", **floor}
    assert why["sensor"] == "set" and config.chosen
    config, why = choose_settings(SceneConfig(voxel_size=0.05, sensor={"edge_weight": 2.0}), frame)
    assert config.sensor.model_dump() == {**SENSOR_PRESETS["structured_light"], "edge_weight": 2.0,
                                          "family": "structured_light", **floor}
    assert (config.voxel_size, why["voxel_size"]) == (0.05, "set") and why["sensor"].startswith("detected")


def test_a_scene_chooses_once_from_its_first_frame_and_keeps_it(shelf):
    scene = Scene(SceneConfig(), keep_frames=True)
    assert scene.stats()["voxel_size"] is None and scene.stats()["chosen"] == {}
    assert len(scene.decode()) == len(scene.gaussians()) == 0  # nothing to decode before the choice
    report = scene.fold(shelf[0])
    expected = default_voxel_size([shelf[0]])
    assert scene.config.voxel_size == expected and scene.config.chosen
    assert (report.sensor, report.sensor_chosen) == (DEFAULT_FAMILY, scene.chosen["sensor"])
    assert scene.stats()["chosen"]["voxel_size"] == "6 pixel footprints at the first frame's median depth"
    for frame in shelf[1:]:  # later frames, nearer or farther, change nothing
        assert scene.fold(frame).sensor == DEFAULT_FAMILY
    assert scene.config.voxel_size == expected
    config = scene.config
    scene.remove_frames([0])  # the frame that chose is gone; the choice stays for the scene's life
    assert scene.config == config
    scene.rollback(scene.undo_floor)
    assert scene.config == config
    again = Scene.from_bytes(scene.to_bytes())
    assert (again.config, again.chosen, again.digest()) == (config, scene.chosen, scene.digest())


def test_the_same_frames_with_the_chosen_size_given_fold_the_same_scene(shelf):
    chosen = Scene(SceneConfig())
    for frame in shelf:
        chosen.fold(frame)
    given = Scene(SceneConfig(voxel_size=default_voxel_size([shelf[0]])))
    for frame in shelf:
        given.fold(frame)
    assert given.config == chosen.config and given.digest() == chosen.digest()


def test_a_first_frame_without_depth_is_refused_naming_voxel_size_and_changes_nothing(shelf):
    scene = Scene(SceneConfig())
    with pytest.raises(ValueError, match="^voxel_size: the session chooses it from its first frame with depth"):
        scene.fold(dataclasses.replace(shelf[0], depth=None))
    assert (scene.frames, scene.config, scene.chosen) == (0, SceneConfig(), {})
    # with the voxel size given, such a frame waits for a partner; the sensor takes the default family
    scene = Scene(SceneConfig(voxel_size=0.01))
    assert scene.fold(dataclasses.replace(shelf[0], depth=None)).sensor_chosen == "default: no depth to detect it from"


@pytest.mark.parametrize("out_of_range", [lambda d: torch.where(d > 0, 25.0, 0.0),  # all beyond range.far
                                          lambda d: d * 1000.0], ids=["beyond far", "millimetres as metres"])
def test_a_first_frame_whose_depth_is_out_of_range_chooses_no_voxel_and_says_where_its_depth_lies(shelf, out_of_range):
    """The voxel is chosen from the depth a scene folds: a first frame with none in range (all beyond
    range.far, or millimetres sent as metres) is refused naming voxel_size and its depth's median,
    rather than fixing for the scene's life a voxel sized by depth that made no voxel; the good
    frames after it choose as they do alone."""
    far = dataclasses.replace(shelf[0], depth=out_of_range(shelf[0].depth))
    scene = Scene(SceneConfig())
    with pytest.raises(ValueError, match=r"^voxel_size: no valid depth .* its depth lies at [0-9.]+ m \(median\), outside "
                                         r"range.near..range.far = 0.05..20 m; is it in metres\?"):
        scene.fold(far)
    assert (scene.frames, scene.config, scene.chosen) == (0, SceneConfig(), {})
    for frame in shelf[:3]:
        scene.fold(frame)
    alone = Scene(SceneConfig())
    for frame in shelf[:3]:
        alone.fold(frame)
    assert scene.config == alone.config and scene.digest() == alone.digest()


def test_a_refused_first_frame_chooses_nothing(shelf):
    scene = Scene(SceneConfig(features={"backend": "client"}))
    with pytest.raises(ValueError, match="^features: "):
        scene.fold(shelf[0])  # carries no client features
    assert (scene.config, scene.chosen) == (SceneConfig(features={"backend": "client"}), {})


def test_client_features_keep_the_first_frames_channels_for_the_scenes_life(shelf):
    """Each count of client channels is projected to ``features.dim`` its own way: a frame with
    another count would mix unrelated channels in. The first frame's count is the scene's, through a
    snapshot too; a frame with another is refused naming features, and changes nothing."""
    import torch

    def with_features(frame, channels):
        return dataclasses.replace(frame, features=torch.rand(frame.height // 4, frame.width // 4, channels))

    scene = Scene(SceneConfig(voxel_size=0.01, features={"backend": "client"}))
    assert not scene.config.chosen
    scene.fold(with_features(shelf[0], 8))
    assert scene.config.features.client_channels == 8 and scene.config.chosen
    before = scene.digest()
    with pytest.raises(ValueError, match=r"^features: expected 8 channels a pixel \(this session's, its first frame's\), got 16"):
        scene.fold(with_features(shelf[1], 16))
    assert scene.digest() == before and scene.frames == 1
    again = Scene.from_bytes(scene.to_bytes())
    with pytest.raises(ValueError, match="^features: expected 8 channels"):
        again.fold(with_features(shelf[1], 4))
    again.fold(with_features(shelf[1], 8))
    assert again.frames == 2
    recorded = SceneConfig(voxel_size=0.01, features={"backend": "client"})  # as a session's files hold it before
    assert filled_from(recorded, scene.config) == scene.config


def test_settings_recorded_before_the_choice_name_the_same_scene(shelf):
    scene = Scene(SceneConfig(sensor={"registration_px": 1.0}))
    scene.fold(shelf[0])
    assert filled_from(SceneConfig(sensor={"registration_px": 1.0}), scene.config) == scene.config
    assert filled_from(SceneConfig(sensor={"registration_px": 2.0}), scene.config) != scene.config
    assert filled_from(scene.config, SceneConfig(voxel_size=1.0)) == scene.config  # nothing left open


def test_evidence_outside_a_scene_uses_the_family_of_its_frames_depth(first_frames):
    depth = first_frames["sun3d_studyroom"].depth
    assert SceneConfig().sensor.in_effect(depth).family == "structured_light"
    named = SceneConfig(sensor={"family": "hololens"}).sensor
    assert named.in_effect(depth) == named.with_preset() and named.with_preset().chosen
