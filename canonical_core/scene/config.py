"""Scene settings: one validated, serialisable record shared by the fold, the batch reference and decode."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Literal, get_args

Weighting = Literal["full", "no_reliability", "no_similarity", "average"]
FeatureBackend = Literal["default", "client"]

# Voxel indices are packed into one int64 key with 21 bits per axis: a lattice of +-2^20 voxels
# per axis around the fixed origin (+-4 km at 4 mm), which is "unbounded" for any capture.
KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)


@dataclass(frozen=True)
class SceneConfig:
    """Settings of a scene.

    Attributes:
        voxel_size: edge length of the sparse lattice's voxels, in the scene's unit (metres).
        feature_dim: L, channels of the fused features (the default extractor's output size).
        feature_backend: ``default`` (training-free extractor) or ``client`` (use ``Frame.features``,
            resized to the image and projected to ``feature_dim`` channels).
        weighting: ablation mode of the aggregation rule (``full`` is the paper's rule).
            ``no_reliability`` and ``average`` treat every reliability as 1, in the free-space
            evidence too; ``no_similarity`` and ``average`` drop the cosine factor (see
            `uses_reliability`, `uses_similarity`).
        depth_sigma0, depth_sigma2, depth_sigma_ref: sensor noise model for supplied depth without a
            std: sigma(z) = sigma0 + sigma2 * (z - ref)^2 metres (structured-light/ToF sensors).
        depth_edge_weight: adds weight * (largest depth jump to a valid 8-neighbour) to sigma, so
            "flying pixels" on depth discontinuities get low reliability.
        near, far: depth range accepted from frames, metres; outside it a pixel is ignored.
        eps: the epsilon of F_scene = sum W F / (R_scene + eps).
        max_voxels: cap on the number of voxels (None = unbounded); a fold that would exceed it
            raises instead of folding part of a frame.
        sh_degree: degree of the per-voxel spherical-harmonics colour fit (0 = view-independent).
        sh_regularization: ridge weight, relative to R_scene, pulling the SH fit's higher
            coefficients toward zero (i.e. toward the DC colour) where few view directions were seen.
            A degree-1 term keeps about var / (var + ridge) of its least-squares value, var being
            the weighted variance of its basis over the observations (C1^2 theta^2 / 4 for two
            views theta radians apart): 0.003 trusts views ~20 degrees apart (70 % kept; 0.05
            kept 12 %) and ignores the spread of rays within one view. Measured on the shelf
            evaluation: covered PSNR +0.06 / +0.14 / +0.20 / +0.27 dB at N = 2 / 4 / 8 / 16 over
            0.05, in extrapolation too.
        free_space: fold free-space ("seen-through") evidence and use it in decoding.
        free_space_margin, free_space_sigmas: a voxel is seen through by a ray whose surface lies
            beyond margin * voxel_size + sigmas * sigma(depth) behind the voxel's centre.
        free_space_cell: pixels per side of the cells of a frame's coarse see-through map.
        free_space_history: frames whose maps are kept so voxels created later get their evidence.
        depth_sources: source views a frame without depth is swept against (plane sweep).
        depth_hypotheses: K, depth hypotheses of the sweep (uniform in inverse depth).
        source_window: recent views kept for the sweep (and frames without depth that may wait
            for a partner at once).
        depth_completion: also sweep frames that carry depth, and fill the large holes of their
            depth (beyond ``depth_completion_radius`` pixels from any measured pixel: beyond the
            sensor's range or field of view, dark or specular surfaces) with the swept depth, its
            U_pos as std (`evidence.complete_depth`; only the holes are swept, and a frame
            without holes is not swept at all). Measured pixels are never changed. Off by
            default: frames with depth then skip the sweep (issue 5). On the shelf evaluation it buys
            coverage (all-pixel PSNR) at some covered PSNR; see the evaluation's ``depth_completion``.
        depth_completion_radius: pixels; holes closer than this to a measured pixel stay unfilled.
        depth_denoise_radius: pixels; a frame whose depth is far rougher than its noise model (its
            std, or the sensor model) gets the median of a (2 radius + 1)^2 window instead, with
            that median's std (`evidence.denoise`; 0 turns it off). Clean sensor depth is never
            touched. Measured on the shelf evaluation at depth noise 0.25: see README.
        free_space_dominance: decoding drops voxels whose free-space evidence exceeds this
            multiple of their support R_scene. 2, not 1: the see-through weight counts rays as if
            the voxel faced the camera, which overstates it up to 2x for surfaces seen at 60 deg.
        opacity_slope: a of the decoder's analytic (untrained) opacity logit a r + b, r being
            support in typical views (see `decode.decoder`). At 30 (with b = 0), a voxel with next
            to no support is half opaque, a fiftieth of one typical view's support 64 %, a tenth
            95 %. Steep because the weakly supported voxels of clean depth (depth edges, thin or
            sparse geometry) are mostly real surface. Measured on the shelf evaluation against 10
            (b = -3): all-pixel PSNR +0.3-0.5 dB at every N, covered within 0.05 dB, depth
            agreement -0.02 to -0.03; see README. Both line settings shape a new session's
            untrained decoder (`decode.decoder.OPACITY_SLOPE`, `OPACITY_BIAS` are their defaults);
            a loaded snapshot keeps its decoder's own parameters.
        opacity_bias: b of the same line, the logit of a voxel without reliable support. 0 since
            rough depth is denoised (`depth_denoise_radius`): -3 was there to keep the scattered
            voxels of noisy depth see-through, and with denoising it only dimmed real surface.
            Measured against -3 (shelf evaluation, N = 2 / 4 / 8 / 16): all-pixel PSNR +0.19 /
            +0.10 / +0.07 / +0.05 dB clean and +0.40 / +0.25 / +0.20 / +0.19 dB under depth noise
            0.25, covered within 0.02 dB clean (0.1 dB noisy), depth agreement 0.003-0.013 lower.
            With denoising off, noisy depth wants -3 (at 0 and slope 10, noise 0.25 at N = 4 fell
            from 11.59 to 11.43 dB).
        colour_solve_views: keep this many input views (colour and camera, spread over the
            stream: `scene.keyframes`) and solve the decoded Gaussians' colours against them
            (`decode.solve_colours`: renders made to reproduce the inputs; geometry and opacity
            unchanged; the SH coefficients up to degree 1 are solved, so colour may change with
            the view). 0 (default) turns it off. Measured on the shelf evaluation (every input
            kept): held-out covered PSNR +1.6 to +2.6 dB, all-pixel +0.4 to +0.9 dB at N = 2-16;
            it costs a decode seconds instead of milliseconds (`bench/colour_solve.py`). See the
            evaluation's ``colour_solve``.
        colour_solve_scale: the kept views' size relative to the input (0.5: a quarter of the
            pixels, 0.23 MB per 640x480 view). Measured on the shelf at N = 16 against full size:
            held-out 14.78 / 20.82 dB (all-pixel / covered) against 14.84 / 21.04, solve 3.1 s
            against 10.2 s on 2 cores (`bench/colour_solve.py`).
    """

    voxel_size: float
    feature_dim: int = 16
    feature_backend: FeatureBackend = "default"
    weighting: Weighting = "full"
    depth_sigma0: float = 0.0012
    depth_sigma2: float = 0.0019
    depth_sigma_ref: float = 0.4
    depth_edge_weight: float = 0.5
    near: float = 0.05
    far: float = 20.0
    eps: float = 1e-8
    max_voxels: int | None = None
    sh_degree: int = 1
    sh_regularization: float = 0.003
    free_space: bool = True
    free_space_margin: float = 2.0
    free_space_sigmas: float = 3.0
    free_space_cell: int = 8
    free_space_history: int = 64
    free_space_dominance: float = 2.0
    depth_sources: int = 2
    depth_hypotheses: int = 64
    source_window: int = 4
    depth_completion: bool = False
    depth_completion_radius: int = 6
    depth_denoise_radius: int = 7
    opacity_slope: float = 30.0
    opacity_bias: float = 0.0
    colour_solve_views: int = 0
    colour_solve_scale: float = 0.5

    @property
    def uses_reliability(self) -> bool:
        """Whether the weighting uses R_view (else every reliability counts as 1)."""
        return self.weighting in ("full", "no_similarity")

    @property
    def uses_similarity(self) -> bool:
        """Whether W carries the factor max(0, cos(F, F_rep))."""
        return self.weighting in ("full", "no_reliability")

    def __post_init__(self):
        def positive(name, value):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{name}: expected a positive finite number, got {value!r}")

        positive("voxel_size", self.voxel_size)
        positive("far", self.far)
        positive("eps", self.eps)
        for name in ("depth_sigma0", "depth_sigma2", "depth_edge_weight", "near", "depth_sigma_ref",
                     "sh_regularization", "free_space_margin", "free_space_sigmas", "free_space_dominance"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{name}: expected a non-negative finite number, got {v!r}")
        positive("opacity_slope", self.opacity_slope)
        if isinstance(self.opacity_bias, bool) or not isinstance(self.opacity_bias, (int, float)) or not math.isfinite(self.opacity_bias):
            raise ValueError(f"opacity_bias: expected a finite number, got {self.opacity_bias!r}")
        if self.near >= self.far:
            raise ValueError(f"near: must be below far ({self.near} >= {self.far})")
        if isinstance(self.feature_dim, bool) or not isinstance(self.feature_dim, int) or not 1 <= self.feature_dim <= 512:
            raise ValueError(f"feature_dim: expected an integer in [1, 512], got {self.feature_dim!r}")
        if self.weighting not in get_args(Weighting):
            raise ValueError(f"weighting: expected one of {list(get_args(Weighting))}, got {self.weighting!r}")
        if self.feature_backend not in get_args(FeatureBackend):
            raise ValueError(f"feature_backend: expected one of {list(get_args(FeatureBackend))}, got {self.feature_backend!r}")
        for name, lo, hi in (("sh_degree", 0, 3), ("free_space_cell", 1, 64), ("free_space_history", 1, 100_000),
                             ("depth_sources", 1, 8), ("depth_hypotheses", 2, 512), ("source_window", 1, 64),
                             ("depth_completion_radius", 1, 256), ("depth_denoise_radius", 0, 32),
                             ("colour_solve_views", 0, 64)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{name}: expected an integer in [{lo}, {hi}], got {v!r}")
        for name in ("free_space", "depth_completion"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected true or false, got {getattr(self, name)!r}")
        if isinstance(self.colour_solve_scale, bool) or not isinstance(self.colour_solve_scale, (int, float)) \
                or not 0 < self.colour_solve_scale <= 1:
            raise ValueError(f"colour_solve_scale: expected a number in (0, 1], got {self.colour_solve_scale!r}")
        if self.max_voxels is not None and (isinstance(self.max_voxels, bool) or not isinstance(self.max_voxels, int) or self.max_voxels <= 0):
            raise ValueError(f"max_voxels: expected a positive integer or None, got {self.max_voxels!r}")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SceneConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{unknown[0]}: unknown scene setting (known: {sorted(known)})")
        return cls(**d)
