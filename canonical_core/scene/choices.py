"""Settings a scene may leave to its first frame: the voxel size and the depth sensor's family.

`choose_settings` fills what a `SceneConfig` leaves open from the first frame a scene folds, once;
the scene then keeps the result for its life (snapshots, corrections and rollbacks included):

- ``voxel_size`` None: `default_voxel_size` of that frame, ``VOXEL_PIXELS`` pixel footprints at its
  median depth, the evaluation's rule (`eval.run`), so a voxel covers a similar patch of pixels on
  any capture. It needs depth: a first frame without depth is refused, naming ``voxel_size``.
- ``sensor.family`` ``auto``: the family its depth's quantisation shows (`detect_family`), else
  `config.DEFAULT_FAMILY`; the family's preset then fills every sensor value left None.

Each choice comes with the reason a fold report and the session's stats show.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..config import DEFAULT_FAMILY, SceneConfig
from ..frame import Frame

__all__ = ["VOXEL_PIXELS", "choose_settings", "default_voxel_size", "detect_family", "disparity_step", "filled_from"]

VOXEL_PIXELS = 6.0  # voxel edge in pixel footprints at the median depth

# Disparity quantisation (module `detect_family`): depth levels spaced c z^2 apart. The exponent of
# the spacing must be 2 within this, and the levels' c agree within this log-spread (median absolute
# deviation of log c), over at least this many gaps and a depth span of at least this ratio.
EXPONENT_TOLERANCE = 0.3
MAX_LOG_SPREAD = 0.1
MIN_GAPS = 16
MIN_DEPTH_RATIO = 1.5
# c, 1/m, of the families whose disparity is quantised: 1/8 pixel at f B about 40 px m (Kinect v1,
# PrimeSense: 580 px x 7.5 cm) is about 2.9e-3; 1/32 pixel at f B 20 to 37 px m (RealSense D4xx) is
# 0.85e-3 to 1.6e-3.
STRUCTURED_LIGHT_STEP = 2e-3
ACTIVE_STEREO_STEP = 0.4e-3


def default_voxel_size(frames: Sequence[Frame]) -> float:
    """``VOXEL_PIXELS`` pixel footprints (z / f) at the median valid depth of ``frames``, to 2
    significant digits. Raises ValueError naming ``voxel_size`` when they carry no valid depth."""
    depths = [f.depth[f.depth > 0] for f in frames if f.depth is not None]
    depths = torch.cat(depths) if depths else torch.zeros(0)
    if depths.numel() == 0:
        raise ValueError("voxel_size: no valid depth to choose it from (it is 6 pixel footprints at the median depth)")
    focal = float(np.mean([(f.camera.fx + f.camera.fy) / 2 for f in frames]))
    size = VOXEL_PIXELS * float(depths.median()) / focal
    return float(f"{size:.2g}")


def disparity_step(
    depth: Tensor | np.ndarray,  # [H, W] metres, 0 = no measurement
) -> float | None:  # c, 1/m, or None
    """c where the distinct depth values lie c z^2 apart, as depth computed from a disparity
    quantised in fixed sub-pixel steps does (structured light, active stereo); None where they do
    not (time of flight, depth stored in a fixed unit finer than the disparity's steps, float depth)
    or the depth spans too little range to tell. Why: the step c = s / (f B) is the sensor's own
    fingerprint, s its sub-pixel step and f B its focal length times baseline."""
    z = np.asarray(depth, dtype=np.float64)
    levels = np.unique(z[z > 0])
    if levels.size <= MIN_GAPS or levels[-1] < MIN_DEPTH_RATIO * levels[0]:
        return None
    gaps, mid = np.diff(levels), (levels[1:] + levels[:-1]) / 2
    exponent, log_c = np.polyfit(np.log(mid), np.log(gaps), 1)
    log_steps = np.log(gaps / mid**2)
    spread = float(np.median(np.abs(log_steps - np.median(log_steps))))
    if abs(exponent - 2.0) > EXPONENT_TOLERANCE or spread > MAX_LOG_SPREAD:
        return None
    return float(np.exp(np.median(log_steps)))


def detect_family(
    depth: Tensor | np.ndarray | None,  # [H, W] metres, or None for a frame without depth
) -> tuple[str, str]:  # (family, why)
    """The sensor family a frame's depth shows, and why: disparity steps of structured light's size
    (c >= `STRUCTURED_LIGHT_STEP`) or of active stereo's, else `DEFAULT_FAMILY` (time of flight,
    HoloLens and phone LiDAR depth carry no such fingerprint)."""
    if depth is None:
        return DEFAULT_FAMILY, "default: the first frame carries no depth"
    step = disparity_step(depth)
    if step is None:
        return DEFAULT_FAMILY, "default: the first frame's depth shows no disparity quantisation"
    found = f"detected from depth quantisation (levels {step:.2g} z^2 apart)"
    if step >= STRUCTURED_LIGHT_STEP:
        return "structured_light", found
    if step >= ACTIVE_STEREO_STEP:
        return "active_stereo", found
    return DEFAULT_FAMILY, f"default: depth levels {step:.2g} z^2 apart match no family"


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
        changes["voxel_size"] = default_voxel_size([frame])
        why["voxel_size"] = f"{VOXEL_PIXELS:g} pixel footprints at the first frame's median depth"
    if not config.sensor.chosen:
        family = config.sensor.family
        if family == "auto":
            family, why["sensor"] = detect_family(depth)
        changes["sensor"] = config.sensor.with_preset(family)
    return (config.replace(**changes) if changes else config), why


def filled_from(config: SceneConfig, made: SceneConfig) -> SceneConfig:
    """``config`` with what it leaves open as ``made`` chose it: equal to ``made`` when ``made`` is
    the settings of a scene that started with ``config``. Why: a session's files may record its
    settings from before the first frame and from after it, and both name the same session."""
    if config.chosen:
        return config
    given = {k: v for k, v in config.sensor.model_dump().items() if v not in (None, "auto")}
    return config.replace(voxel_size=made.voxel_size if config.voxel_size is None else config.voxel_size,
                          sensor={**made.sensor.model_dump(), **given})
