"""Sensor presets: the depth noise model of each sensor family, from its published noise model,
in the settings' one model sigma(z) = sigma0 + sigma2 (z - sigma_ref)^2 metres plus ``edge_weight``
times the largest depth jump to a neighbour (`SensorNoise`). A family's values fill the ``sensor``
settings a scene leaves None; a value set explicitly wins over its family's.

The structured-light preset is the model the project has used from the start (and that the
leave-one-capture-out tuning kept, `eval.tuning`): it is also `DEFAULT_FAMILY`, the family of depth
whose statistics name no family (`scene.choices`).
"""

from __future__ import annotations

from typing import Literal

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
