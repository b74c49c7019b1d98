"""Settings a scene may leave to its first frame: the voxel size, the depth sensor's family and the
channels of client features.

`choose_settings` fills what a `SceneConfig` leaves open from the first frame a scene folds, once;
the scene then keeps the result for its life (snapshots, corrections and rollbacks included):

- ``voxel_size`` None: `default_voxel_size` of that frame, ``VOXEL_PIXELS`` pixel footprints at its
  median depth (of the depth within ``range``: what the scene folds), the rule `canonical eval`
  uses for its captures too (`eval.run`), so a voxel covers a similar patch of pixels on any
  capture. It needs depth: a first frame without depth, or with none in range (millimetres sent as
  metres), is refused, naming ``voxel_size`` and where its depth lies.
- ``sensor.family`` ``auto``: the family its depth's quantisation shows (`config.detect_family`),
  else `config.DEFAULT_FAMILY`; the family's preset then fills every sensor value left None.
- ``features.client_channels`` None, with client features: the channels of that frame's features.

Each choice comes with the reason a fold report and the session's stats show.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ..config import SceneConfig, detect_family
from ..frame import Frame

__all__ = ["VOXEL_PIXELS", "choose_settings", "choose_without_frame", "default_voxel_size", "filled_from"]

# voxel edge in pixel footprints at the median depth: fine enough to keep a pixel's detail within a
# few voxels, coarse enough that one view gives each voxel several observations
VOXEL_PIXELS = 6.0


def default_voxel_size(frames: Sequence[Frame], near: float = 0.0, far: float = float("inf")) -> float:
    """``VOXEL_PIXELS`` pixel footprints (z / f) at the median valid depth of ``frames`` (within
    (``near``, ``far``): the depth a scene folds; the evaluation gives no range), to 2 significant
    digits. Raises ValueError naming ``voxel_size`` when they carry none, saying where their depth lies."""
    valid = [f.depth[f.depth > 0] for f in frames if f.depth is not None]
    valid = torch.cat(valid) if valid else torch.zeros(0)
    depths = valid[(valid > near) & (valid < far)]
    if depths.numel() == 0:
        found = "" if valid.numel() == 0 else (
            f": its depth lies at {float(valid.median()):g} m (median), outside range.near..range.far = {near:g}..{far:g} m; "
            "is it in metres?")
        raise ValueError(f"voxel_size: no valid depth to choose it from (it is 6 pixel footprints at the median depth){found}")
    focal = float(np.mean([(f.camera.fx + f.camera.fy) / 2 for f in frames]))
    size = VOXEL_PIXELS * float(depths.median()) / focal
    return float(f"{size:.2g}")


def choose_settings(config: SceneConfig, frame: Frame | None) -> tuple[SceneConfig, dict[str, str]]:
    """``config`` with what it leaves open chosen from ``frame`` (module docstring; None: no frame,
    for a config that leaves only a named family's values open), and why each setting has its value:
    ``{"voxel_size": ..., "sensor": ...}`` ("set" where ``config`` set it). Raises ValueError naming
    ``voxel_size`` when it is to be chosen and ``frame`` has no valid depth."""
    depth = None if frame is None else frame.depth
    changes: dict = {}
    why = {"voxel_size": "set", "sensor": "set"}
    if config.voxel_size is None:
        if depth is None:
            raise ValueError("voxel_size: the session chooses it from its first frame with depth, and this frame has "
                             "none: send a frame with depth first, or set voxel_size")
        changes["voxel_size"] = default_voxel_size([frame], config.range.near, config.range.far)
        why["voxel_size"] = f"{VOXEL_PIXELS:g} pixel footprints at the first frame's median depth"
    if not config.sensor.chosen:
        family = config.sensor.family
        if family == "auto":
            family, why["sensor"] = detect_family(depth)
        changes["sensor"] = config.sensor.with_preset(family)
    features = config.features
    if features.backend == "client" and features.client_channels is None and frame is not None \
            and frame.features is not None:  # a frame without them is refused by its fold
        changes["features"] = features.model_copy(update={"client_channels": int(frame.features.shape[-1])})
    return (config.replace(**changes) if changes else config), why


def choose_without_frame(config: SceneConfig) -> tuple[SceneConfig, dict[str, str]]:
    """`choose_settings` of a config that needs no frame for it (its voxel size set, its family
    named: a scene then knows its settings from the start), else ``config`` and no reasons yet."""
    if config.voxel_size is None or config.sensor.family == "auto":
        return config, {}
    return choose_settings(config, None)


def filled_from(config: SceneConfig, made: SceneConfig) -> SceneConfig:
    """``config`` with what it leaves open as ``made`` chose it: equal to ``made`` when ``made`` is
    the settings of a scene that started with ``config``. Why: a session's files may record its
    settings from before the first frame and from after it, and both name the same session."""
    if config.chosen:
        return config
    given = {k: v for k, v in config.sensor.model_dump().items() if v not in (None, "auto")}
    channels = config.features.client_channels
    return config.replace(voxel_size=made.voxel_size if config.voxel_size is None else config.voxel_size,
                          sensor={**made.sensor.model_dump(), **given},
                          features={**config.features.model_dump(), "client_channels":
                                    made.features.client_channels if channels is None else channels})
