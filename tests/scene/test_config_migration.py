"""Files written with the flat settings layout (every setting at the top level) still load: a snapshot
(tests/fixtures/scene_v4.snap, see tests/fixtures/README.md) decodes to what it decoded to when it was
written, and a session's meta.json gives the same settings in their groups."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from canonical_core import Scene, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.config import FLAT_NAMES, migrate_flat
from canonical_core.scene.selection import decoded_rows
from canonical_core.scene.fields import fields_from_sums

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


@pytest.fixture(scope="module")
def loaded() -> Scene:
    return Scene.load(FIXTURES / "scene_v4.snap")


def test_flat_snapshot_settings_land_in_their_groups(loaded):
    c = loaded.config
    assert (c.voxel_size, c.features.dim) == (0.15, 4)
    assert (c.free_space.enabled, c.free_space.margin, c.depth.hypotheses, c.sensor.edge_weight) == (True, 2.5, 32, 0.4)
    assert (c.decoder.opacity_slope, c.decoder.opacity_bias, c.decoder.sh_regularization) == (25.0, -1.0, 0.004)
    assert (c.research.weighting, c.research.eps) == ("full", 1e-8)
    # and every other setting is its default, but the weight floor (0: it did not exist then) and the colour
    # solve, which the snapshot has off (written when that was the default): a loaded scene keeps the
    # settings it was made with; the sensor values, written before the families, under the family of the
    # model they were (registration_px, newer than the layout, is its preset's)
    assert c == SceneConfig(voxel_size=0.15, features={"dim": 4}, free_space={"margin": 2.5}, depth={"hypotheses": 32},
                            sensor={"family": "structured_light", "sigma0": 0.0012, "sigma2": 0.0019, "sigma_ref": 0.4,
                                    "edge_weight": 0.4, "registration_px": 0.0, "weight_floor": 0.0},
                            colour_solve={"views": 0},
                            decoder={"opacity_slope": 25.0, "opacity_bias": -1.0, "sh_regularization": 0.004})


# the fixture's state as the map stores it since records keep the representative's feature as its 8-bit
# direction and its position in local voxel units, and the feature, colour and position sums and the SH
# sums as float16 means and central moments (`scene.stored`): the file's float32 sums and world
# positions are stored so on loading, and this digest pins that conversion (the file's own digest, in
# its expected.json, was of the float32 sums)
STORED_DIGEST = "f5d34d4bcff04e5ea4cc607299c6aa6ccfdf05bf56e8050fa8b0fb432b476257"
# how far its decode may lie from what it decoded to when written: opacities do not move; positions
# move by float16's rounding of the stored position mean (a thousandth of its 0.15 m voxel at most),
# F_scene by float16's rounding of the stored feature sums, SH by the colour mean's (2^-11 / C0 at most),
# and scales, rotations and SH by the
# stored moments' and the decoded rows' float16 (`scene.decoded.HALF_PARTS`)
DECODE_ATOL = {"means": 1.5e-4, "opacities": 1e-6, "scales": 1e-4, "quats": 1e-3, "features": 1e-3, "sh": 3e-3}


def test_flat_snapshot_keeps_its_state_and_decode(loaded):
    expected = json.loads((FIXTURES / "scene_v4.expected.json").read_text())
    assert (loaded.digest(), loaded.frames, len(loaded)) == (STORED_DIGEST, expected["frames"], expected["voxels"])
    decoded = loaded.decode()
    stored = np.load(FIXTURES / "scene_v4.decoded.npz")
    assert len(decoded) == expected["gaussians"]
    # a rotation is compared where the covariance fixes it: where a voxel's points lie on a line (a few
    # observations in a row), the axes about that line are any and the smallest rounding turns them
    sums = loaded.sums()
    rows = decoded_rows(sums, 0.0, loaded.config).rows
    cov = fields_from_sums(sums, loaded.config, sort=False)["position_cov"][torch.from_numpy(rows)].double()
    determined = (torch.linalg.eigvalsh(cov)[:, 1] > 1e-4 * loaded.config.voxel_size**2).numpy()
    assert len(rows) == len(decoded) and determined.mean() > 0.3
    for name in stored.files:
        ours, theirs = getattr(decoded, name).numpy(), stored[name]
        if name == "quats":
            ours, theirs = ours[determined], theirs[determined]
        np.testing.assert_allclose(ours, theirs, atol=DECODE_ATOL[name], err_msg=name)


def test_a_loaded_flat_snapshot_folds_on_and_saves_in_the_grouped_layout(loaded, tmp_path):
    frame = list(synthetic_rgbd(num_frames=3, width=64, height=48, seed=3))[2]
    scene = Scene.from_bytes(loaded.to_bytes())
    scene.fold(frame)
    scene.save(tmp_path / "s.snap")
    again = Scene.load(tmp_path / "s.snap")
    assert again.config == loaded.config and again.digest() == scene.digest()
    header = json.loads(np.load(tmp_path / "s.snap")["header"].tobytes().decode())
    assert header["config"]["free_space"]["margin"] == 2.5 and "free_space_margin" not in header["config"]
    assert torch.equal(again.decode().opacities, scene.decode().opacities)


def test_flat_session_meta_migrates():
    meta = json.loads((FIXTURES / "session_meta_v1.json").read_text())
    assert "free_space_margin" in meta["config"]  # the fixture is in the flat layout
    config = SceneConfig.from_dict(meta["config"])
    assert (config.voxel_size, config.colour_solve.views, config.depth.completion) == (0.004, 4, True)
    assert (config.free_space.enabled, config.depth.denoise_radius) == (False, 0)
    assert config.decoder.opacity_bias == config.opacity_bias == -3.0
    assert SceneConfig.from_dict(config.to_dict()) == config
    assert config.sensor.weight_floor == 0.0 and SceneConfig(voxel_size=0.004).sensor.weight_floor == 0.5  # folded without one


def test_migration_moves_every_flat_name_and_only_those():
    flat = {old: None for old in FLAT_NAMES} | {"voxel_size": 1.0, "free_space": True}
    out = migrate_flat(flat)
    assert set(out) == {"voxel_size", "sensor", "free_space", "depth", "decoder", "research", "range", "features",
                        "colour_solve"}
    # + free_space.enabled, + sensor.family (a whole earlier sensor group gets its family)
    assert sum(len(group) for name, group in out.items() if name != "voxel_size") == len(FLAT_NAMES) + 2
    grouped = SceneConfig(voxel_size=1.0).to_dict()
    assert migrate_flat(grouped) == grouped


def test_migration_refuses_a_setting_given_twice():
    with pytest.raises(ValueError, match=r"^free_space: given both as a group and as flat settings \(\['margin'\]\)"):
        SceneConfig.from_dict({"voxel_size": 1.0, "free_space": {"margin": 1.0}, "free_space_margin": 2.0})
    with pytest.raises(ValueError, match="^config: expected a mapping"):
        SceneConfig.from_dict([("voxel_size", 1.0)])


def test_an_earlier_sensor_group_gets_the_family_of_its_model_and_a_partial_one_stays_open():
    earlier = {"sigma0": 0.002, "sigma2": 0.001, "sigma_ref": 0.5, "edge_weight": 0.5, "registration_px": 2.0}
    config = SceneConfig.from_dict({"voxel_size": 0.01, "sensor": earlier})
    assert config.sensor.family == "structured_light" and config.chosen  # every value as it was written
    assert config.sensor.model_dump() == {**earlier, "family": "structured_light", "weight_floor": 0.0}  # the floor did not exist then
    partial = SceneConfig.from_dict({"voxel_size": 0.01, "sensor": {"sigma0": 0.002}})
    assert partial.sensor.family == "auto" and partial.sensor.sigma2 is None and not partial.chosen
