"""SceneConfig: every setting's bounds and types, unknown settings, the groups, round trips, the public
(HTTP and CLI) subset and the derived opacity intercept."""

from __future__ import annotations

import math
import re

import pytest
from pydantic import BaseModel

from canonical_core.config import (
    BIAS_WITH_DENOISING,
    BIAS_WITHOUT_DENOISING,
    FLAT_NAMES,
    FreeSpace,
    SceneConfig,
    parse_setting,
    public_model,
    settings_from_pairs,
)

INF = math.inf
# path -> (kind, lowest accepted, highest accepted, exclusive lower bound?); written out here, not read
# from the definition, so that a changed bound fails a test.
BOUNDS = {
    "voxel_size": (float, 1e-5, 100.0, False),
    "max_voxels": (int, 1, 2**31 - 1, False),
    "sh_degree": (int, 0, 3, False),
    "range.near": (float, 0.0, INF, False),
    "range.far": (float, 0.0, 1e5, True),
    "features.dim": (int, 1, 512, False),
    "features.client_channels": (int, 1, 512, False),
    "colour_solve.views": (int, 0, 64, False),
    "colour_solve.scale": (float, 0.0, 1.0, True),
    "colour_solve.refresh": (int, 1, 1_000_000, False),
    "sensor.sigma0": (float, 0.0, 10.0, False),
    "sensor.sigma2": (float, 0.0, 10.0, False),
    "sensor.sigma_ref": (float, 0.0, 1e5, False),
    "sensor.edge_weight": (float, 0.0, 100.0, False),
    "sensor.registration_px": (float, 0.0, 32.0, False),
    "sensor.weight_floor": (float, 0.0, 1.0, False),
    "free_space.margin": (float, 0.0, INF, False),
    "free_space.sigmas": (float, 0.0, INF, False),
    "free_space.cell": (int, 1, 64, False),
    "free_space.history": (int, 1, 100_000, False),
    "free_space.dominance": (float, 0.0, INF, False),
    "depth.sources": (int, 1, 8, False),
    "depth.hypotheses": (int, 2, 512, False),
    "depth.source_window": (int, 1, 64, False),
    "depth.completion_radius": (int, 1, 256, False),
    "depth.denoise_radius": (int, 0, 32, False),
    "decoder.opacity_slope": (float, 0.0, INF, True),
    "decoder.opacity_bias": (float, -INF, INF, False),
    "decoder.sh_regularization": (float, 0.0, INF, False),
    "research.eps": (float, 0.0, INF, True),
}
CHOICES = {
    "features.backend": ("default", "client"),
    "research.weighting": ("full", "no_reliability", "no_similarity", "average"),
    "model": ("default", "none", "checkpoint.safetensors"),  # names or a checkpoint's path (read when a scene starts)
    "sensor.family": ("auto", "structured_light", "active_stereo", "time_of_flight", "phone_lidar", "hololens"),
}
# settings whose None means "chosen for the scene": from its first frame or its sensor family's preset
OPTIONAL = ("voxel_size", "max_voxels", "features.client_channels", "decoder.opacity_bias", "sensor.sigma0", "sensor.sigma2", "sensor.sigma_ref",
            "sensor.edge_weight", "sensor.registration_px")
SWITCHES = ("depth.completion", "free_space.enabled")


def leaf_paths(model=SceneConfig, prefix="") -> list[str]:
    out = []
    for name, field in model.model_fields.items():
        group = field.annotation if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel) else None
        out += leaf_paths(group, f"{prefix}{name}.") if group else [prefix + name]
    return out


def make(path: str, value, **others) -> SceneConfig:
    settings = {"voxel_size": 0.1, "range": {"far": 1e5}, **others}  # far: room for near's edges, on the lattice
    if path == "range.far":
        settings["range"]["near"] = 0.0
    if path == "voxel_size":  # the finest voxels keep only 2^20 of them between the origin and far
        settings["range"] = {"near": 0.0, "far": 10.0}
    *groups, name = path.split(".")
    target = settings
    for g in groups:
        target = target.setdefault(g, {})
    target[name] = value
    return SceneConfig(**settings)


def read(config: SceneConfig, path: str):
    for part in path.split("."):
        config = getattr(config, part)
    return config


def test_every_setting_has_its_bounds_tested():
    assert sorted([*BOUNDS, *CHOICES, *SWITCHES]) == sorted(leaf_paths())


def edges(kind, lo, hi, exclusive):
    """(accepted values, refused values) at the edges of [lo, hi] (or (lo, hi] when exclusive)."""
    step = 1 if kind is int else 1e-9
    ok, bad = [], [math.nan, INF, -INF] if kind is float else []
    if lo != -INF:
        ok.append(kind(lo + step) if exclusive else kind(lo))
        bad.append(kind(lo) if exclusive else kind(lo - (1 if kind is int else 1e-6)))
    if hi != INF:
        ok.append(kind(hi))
        bad.append(kind(hi + (1 if kind is int else 1e-6)))
    return ok, bad


@pytest.mark.parametrize("path", sorted(BOUNDS))
def test_each_number_accepts_its_edges_and_refuses_past_them_naming_the_field(path):
    kind, lo, hi, exclusive = BOUNDS[path]
    ok, bad = edges(kind, lo, hi, exclusive)
    for value in ok:
        assert read(make(path, value), path) == value
    for value in bad:
        with pytest.raises(ValueError, match=f"^{re.escape(path)}: "):
            make(path, value)


@pytest.mark.parametrize("path", sorted(BOUNDS))
def test_numbers_are_strict_about_types(path):
    kind = BOUNDS[path][0]
    wrong = ["1", True, None] if path not in OPTIONAL else ["1", True]
    if kind is int:
        wrong.append(2.0)  # a float is not an integer, even a whole one
    else:
        assert read(make(path, 1), path) == 1.0 and isinstance(read(make(path, 1), path), float)  # ints widen
    for value in wrong:
        with pytest.raises(ValueError, match=f"^{re.escape(path)}: "):
            make(path, value)


@pytest.mark.parametrize("path", sorted(CHOICES))
def test_choices_accept_their_names_only(path):
    for value in CHOICES[path]:
        assert read(make(path, value), path) == value
    for value in ("median", CHOICES[path][0].upper(), 1, None):
        with pytest.raises(ValueError, match=f"^{re.escape(path)}: "):
            make(path, value)


@pytest.mark.parametrize("path", SWITCHES)
def test_switches_are_booleans_only(path):
    assert read(make(path, False), path) is False and read(make(path, True), path) is True
    for value in (1, 0, "true", None):
        with pytest.raises(ValueError, match=f"^{re.escape(path)}: "):
            make(path, value)


@pytest.mark.parametrize("path", OPTIONAL)
def test_optional_settings_take_none(path):
    assert read(make(path, None), path) is None


def test_far_must_stay_on_the_lattice():
    assert SceneConfig(voxel_size=0.01, range={"far": 0.01 * 2**20}).range.far == 0.01 * 2**20
    with pytest.raises(ValueError, match=r"^range\.far: .* beyond the lattice's 1048576 voxels"):
        SceneConfig(voxel_size=0.01, range={"far": 0.01 * 2**20 * 1.001})


def test_near_must_be_below_far():
    assert SceneConfig(voxel_size=0.01, range={"near": 1.0, "far": 1.0 + 1e-9}).range.near == 1.0
    with pytest.raises(ValueError, match=r"^range\.near: must be below range\.far"):
        SceneConfig(voxel_size=0.01, range={"near": 2.0, "far": 2.0})


def test_voxel_size_and_the_sensor_are_left_to_the_first_frame_by_default():
    config = SceneConfig()
    assert config.voxel_size is None and config.sensor.family == "auto" and config.sensor.sigma0 is None
    assert not config.chosen and not SceneConfig(voxel_size=0.01).chosen  # the sensor is still open
    assert SceneConfig(voxel_size=0.01, sensor=SceneConfig().sensor.with_preset("hololens")).chosen


@pytest.mark.parametrize("settings, message", [
    ({"voxle_size": 0.01}, "^voxle_size: unknown setting$"),
    ({"free_space": {"margn": 1.0}}, r"^free_space\.margn: unknown setting$"),
    ({"free_space_margin": 3.0}, r"^free_space_margin: unknown setting \(it is free_space\.margin now\)$"),
    ({"weighting": "average"}, r"^weighting: unknown setting \(it is research\.weighting now\)$"),
    ({"near": 0.1}, r"^near: unknown setting \(it is range\.near now\)$"),
    ({"colour_solve_views": 4}, r"^colour_solve_views: unknown setting \(it is colour_solve\.views now\)$"),
    ({"free_space": False}, "^free_space: "),
])
def test_unknown_settings_are_named(settings, message):
    with pytest.raises(ValueError, match=message):
        SceneConfig(voxel_size=0.01, **settings)


def test_a_group_built_alone_names_its_path():
    with pytest.raises(ValueError, match=r"^free_space\.cell: "):
        FreeSpace(cell=0)
    assert SceneConfig(voxel_size=0.01, free_space=FreeSpace(cell=4)) == SceneConfig(voxel_size=0.01, free_space={"cell": 4})


def test_round_trip_hash_and_frozen():
    config = SceneConfig(voxel_size=0.02, max_voxels=10, free_space={"margin": 1.5}, depth={"sources": 3},
                         decoder={"opacity_bias": -1.0}, research={"weighting": "average"})
    d = config.to_dict()
    assert d["free_space"]["margin"] == 1.5 and d["research"]["weighting"] == "average"
    again = SceneConfig.from_dict(d)
    assert again == config and hash(again) == hash(config) and again.to_dict() == d
    assert {config: 1}[again] == 1
    assert SceneConfig(voxel_size=0.02) != config
    with pytest.raises(ValueError):
        config.voxel_size = 1.0
    with pytest.raises(ValueError):
        config.free_space.margin = 1.0


def test_replace_changes_only_what_it_names_and_validates():
    config = SceneConfig(voxel_size=0.02, free_space={"margin": 1.5})
    off = config.replace(free_space={"enabled": False}, sh_degree=0)
    assert (off.free_space.enabled, off.free_space.margin, off.sh_degree) == (False, 1.5, 0)
    assert config.free_space.enabled  # unchanged
    with pytest.raises(ValueError, match=r"^free_space\.cell: "):
        config.replace(free_space={"cell": 0})


def test_opacity_intercept_follows_denoising_unless_set():
    assert SceneConfig(voxel_size=0.01).opacity_bias == BIAS_WITH_DENOISING == 0.0
    assert SceneConfig(voxel_size=0.01, depth={"denoise_radius": 0}).opacity_bias == BIAS_WITHOUT_DENOISING == -3.0
    assert SceneConfig(voxel_size=0.01, depth={"denoise_radius": 0}, decoder={"opacity_bias": 0.5}).opacity_bias == 0.5


def test_uses_flags_follow_the_weighting():
    flags = {w: (SceneConfig(voxel_size=1, research={"weighting": w}).uses_reliability,
                 SceneConfig(voxel_size=1, research={"weighting": w}).uses_similarity) for w in CHOICES["research.weighting"]}
    assert flags == {"full": (True, True), "no_reliability": (False, True), "no_similarity": (True, False),
                     "average": (False, False)}


def test_public_model_is_the_definition_without_research():
    Public = public_model("Public")
    assert set(Public.model_fields) == set(SceneConfig.model_fields) - {"research"}
    schema = Public.model_json_schema()
    assert "research" not in schema["properties"] and "required" not in schema  # voxel_size too may be left out
    assert schema["properties"]["sh_degree"]["maximum"] == 3  # bounds come along
    body = Public(voxel_size=0.01, depth={"sources": 3})
    assert SceneConfig(**body.model_dump(exclude_unset=True)) == SceneConfig(voxel_size=0.01, depth={"sources": 3})
    for bad in ({"voxel_size": 0.01, "research": {"weighting": "average"}}, {"voxel_size": "0.01"},
                {"voxel_size": 0.01, "sh_degree": 1.0}):
        with pytest.raises(ValueError):
            Public(**bad)


def test_parsed_settings_build_the_nested_config():
    pairs = [parse_setting(t) for t in ("free_space.margin=3", "free_space.enabled=false", "sh_degree=0")]
    settings = settings_from_pairs(pairs)
    assert settings == {"free_space": {"margin": 3.0, "enabled": False}, "sh_degree": 0}
    config = SceneConfig(voxel_size=0.01, **settings)
    assert (config.free_space.margin, config.free_space.enabled, config.free_space.cell) == (3.0, False, 8)


@pytest.mark.parametrize("text, message", [
    ("research.eps=1", r"^research\.eps: unknown setting"),
    ("depth=3", "^depth: a group"),
    ("voxel_size.x=1", r"^voxel_size\.x: unknown setting"),
    ("depth.hypotheses=1", r"^depth\.hypotheses: input should be greater than or equal to 2"),
    ("max_voxels=0", "^max_voxels: "),
    ("voxel_size=inf", "^voxel_size: input should be a finite number"),
    ("sensor.family=sonar", r"^sensor\.family: input should be 'auto', 'structured_light'"),
    ("decoder.opacity_bias=nan", r"^decoder\.opacity_bias: input should be a finite number"),
    ("=3", "^setting: expected NAME=VALUE"),
])
def test_parse_setting_refuses_naming_the_setting(text, message):
    with pytest.raises(ValueError, match=message):
        parse_setting(text)


def test_the_top_level_is_short():
    assert len(SceneConfig.model_fields) <= 12


def test_the_previous_layout_loads_its_top_level_names_into_their_groups():
    d = {"voxel_size": 0.01, "near": 0.1, "feature_dim": 8, "depth_completion": True, "depth": {"sources": 3},
         "colour_solve_views": 4, "colour_solve_scale": 1.0}
    assert SceneConfig.from_dict(d) == SceneConfig(voxel_size=0.01, range={"near": 0.1}, features={"dim": 8},
                                                   depth={"sources": 3, "completion": True},
                                                   colour_solve={"views": 4, "scale": 1.0},
                                                   sensor={"weight_floor": 0.0})  # folded before the floor
    with pytest.raises(ValueError, match=r"^depth: given both as a group and as flat settings \(\['completion'\]\)"):
        SceneConfig.from_dict({"voxel_size": 0.01, "depth": {"completion": False}, "depth_completion": True})


def test_flat_names_map_onto_existing_fields():
    paths = set(leaf_paths())
    assert all(new in paths for new in FLAT_NAMES.values())
