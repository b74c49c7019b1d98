"""Sensor presets: the depth noise model of each sensor family, from its published noise model,
in the settings' one model sigma(z) = sigma0 + sigma2 (z - sigma_ref)^2 metres plus ``edge_weight``
times the largest depth jump to a neighbour (`SensorNoise`). A family's values fill the ``sensor``
settings a scene leaves None; a value set explicitly wins over its family's.

The structured-light preset is the model the project has used from the start (and that the
leave-one-capture-out tuning kept, `eval.tuning`): it is also `DEFAULT_FAMILY`, the family of depth
whose statistics name no family (`detect_family`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

SensorFamily = Literal["auto", "structured_light", "active_stereo", "time_of_flight", "phone_lidar", "hololens"]

SENSOR_PRESETS: dict[str, dict[str, float]] = {
    # Kinect v1 / PrimeSense / Xtion: axial std 0.0012 + 0.0019 (z - 0.4)^2 m for surfaces up to 60
    # degrees from the ray (Nguyen, Izadi, Lovell, "Modeling Kinect Sensor Noise for Improved 3D
    # Reconstruction and Tracking", 3DIMPVT 2012).
    "structured_light": {"sigma0": 0.0012, "sigma2": 0.0019, "sigma_ref": 0.4, "edge_weight": 0.5,
                         "registration_px": 0.0},
    # RealSense D4xx: RMS depth error = z^2 * subpixel / (f * B) (Grunnet-Jepsen et al., Intel,
    # "Tuning depth cameras for best performance"); subpixel about 0.08 px, f * B about 20 to 37 px m
    # (D435 and D415 at 848 x 480) give 2.2e-3 to 4e-3 z^2: 3e-3 z^2, plus half a millimetre for the
    # 1 mm depth unit and the projector's speckle at short range.
    "active_stereo": {"sigma0": 0.0005, "sigma2": 0.003, "sigma_ref": 0.0, "edge_weight": 0.5,
                      "registration_px": 0.0},
    # Continuous-wave time of flight (Kinect v2, Azure Kinect): about 1.5 mm axial std up to 3 m,
    # growing with range (Fankhauser et al., "Kinect v2 for Mobile Robot Navigation: Evaluation and
    # Modeling", ICAR 2015); Azure Kinect's specification: random error std <= 17 mm, systematic
    # < 11 mm + 0.1 % of z. A few mm plus 0.1 % to 1 % of z in this model: 2 mm + 5e-4 z^2.
    "time_of_flight": {"sigma0": 0.002, "sigma2": 0.0005, "sigma_ref": 0.0, "edge_weight": 0.5,
                       "registration_px": 0.0},
    # Phone LiDAR (iPhone / iPad Pro, ARKit scene depth): about 1 cm at room range (Luetzenburg,
    # Kroeger, Stebner, "Evaluation of the Apple iPhone 12 Pro LiDAR for an Application in
    # Geosciences", Scientific Reports 2021); depth of 256 x 192 upsampled to the colour image, so
    # edges are smeared over a few colour pixels: the registration term covers them.
    "phone_lidar": {"sigma0": 0.005, "sigma2": 0.002, "sigma_ref": 0.0, "edge_weight": 0.5,
                    "registration_px": 4.0},
    # HoloLens 2 research-mode depth (AHAT and long throw, amplitude-modulated time of flight,
    # Ungureanu et al., "HoloLens 2 Research Mode as a Tool for Computer Vision Research", 2020):
    # time-of-flight noise, with a steeper range term for the long-throw mode's far, low-signal
    # returns, 2 mm + 2e-3 z^2 (7 mm at 1.6 m).
    "hololens": {"sigma0": 0.002, "sigma2": 0.002, "sigma_ref": 0.0, "edge_weight": 0.5, "registration_px": 0.0},
}

DEFAULT_FAMILY = "structured_light"  # the family of depth whose statistics name none (module docstring)

# Disparity quantisation (`detect_family`): depth levels spaced c z^2 apart. The exponent of
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


def disparity_step(
    depth: np.ndarray,  # [H, W] metres, 0 = no measurement
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
    exponent, _ = np.polyfit(np.log(mid), np.log(gaps), 1)
    log_steps = np.log(gaps / mid**2)
    spread = float(np.median(np.abs(log_steps - np.median(log_steps))))
    if abs(exponent - 2.0) > EXPONENT_TOLERANCE or spread > MAX_LOG_SPREAD:
        return None
    return float(np.exp(np.median(log_steps)))


def detect_family(
    depth: np.ndarray | None,  # [H, W] metres, or None for a frame without depth
) -> tuple[str, str]:  # (family, why)
    """The sensor family a frame's depth shows, and why: disparity steps of structured light's size
    (c >= `STRUCTURED_LIGHT_STEP`) or of active stereo's, else `DEFAULT_FAMILY` (time of flight,
    HoloLens and phone LiDAR depth carry no such fingerprint)."""
    if depth is None:
        return DEFAULT_FAMILY, "default: no depth to detect it from"
    step = disparity_step(depth)
    if step is None:
        return DEFAULT_FAMILY, "default: the depth shows no disparity quantisation"
    found = f"detected from depth quantisation (levels {step:.2g} z^2 apart)"
    if step >= STRUCTURED_LIGHT_STEP:
        return "structured_light", found
    if step >= ACTIVE_STEREO_STEP:
        return "active_stereo", found
    return DEFAULT_FAMILY, f"default: depth levels {step:.2g} z^2 apart match no family"
