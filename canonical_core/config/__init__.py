"""Scene settings: one declarative, validated, serialisable record shared by the fold, the batch
reference and decode.

The pydantic models of `settings` are the single definition of every setting: their types and bounds give
the library's validation (`SceneConfig(...)` raises a ValueError whose message starts with the
setting's path, e.g. ``free_space.margin: ...``), the service's session-create schema
(`public_model`) and the CLI's ``--set NAME=VALUE`` (`parse_setting`).

Layout: a few settings sit at the top level (voxel size, capacity, SH degree, the decoder's
model); everything else lives in groups with defaults: the depth ``range``, the ``features``, the
``colour_solve``, the ``sensor`` noise model, and expert tuning (``free_space``, ``depth``,
``decoder``). The aggregation ablations live in ``research``, which the evaluation's method
definitions set and the public schema leaves out. Types are strict: a string or a boolean is not a number, a float is not an integer.

Example:
    >>> config = SceneConfig(voxel_size=0.01, free_space={"margin": 3.0})
    >>> config.free_space.margin, config.depth.hypotheses
    (3.0, 64)
    >>> SceneConfig.from_dict(config.to_dict()) == config
    True
"""

from .migration import FLAT_NAMES, migrate_flat
from .public import PRIVATE_GROUPS, parse_setting, public_model, settings_from_pairs
from .settings import (
    BIAS_WITH_DENOISING,
    BIAS_WITHOUT_DENOISING,
    KEY_BITS,
    KEY_OFFSET,
    MAX_DEPTH,
    MAX_VOXEL,
    MAX_VOXELS,
    MIN_VOXEL,
    ColourSolve,
    DecoderSettings,
    DepthEstimation,
    DepthRange,
    FeatureBackend,
    FeatureSettings,
    FreeSpace,
    Research,
    SceneConfig,
    SensorNoise,
    SettingsGroup,
    Weighting,
)

__all__ = ["BIAS_WITHOUT_DENOISING", "BIAS_WITH_DENOISING", "FLAT_NAMES", "KEY_BITS", "KEY_OFFSET", "MAX_DEPTH", "MAX_VOXEL",
           "MAX_VOXELS", "MIN_VOXEL", "PRIVATE_GROUPS", "ColourSolve", "DecoderSettings", "DepthEstimation", "DepthRange",
           "FeatureBackend", "FeatureSettings", "FreeSpace", "Research", "SceneConfig", "SensorNoise", "SettingsGroup",
           "Weighting", "migrate_flat", "parse_setting", "public_model", "settings_from_pairs"]
