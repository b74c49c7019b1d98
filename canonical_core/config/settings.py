"""The settings' definition: `SceneConfig` and its groups, pydantic models whose types and bounds are
the validation. Construction raises a ValueError naming the setting's path (``free_space.margin:
...``), not pydantic's multi-line report."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .migration import FLAT_NAMES, migrate_flat
from .sensors import SENSOR_PRESETS, SensorFamily, detect_family

Weighting = Literal["full", "no_reliability", "no_similarity", "average"]
FeatureBackend = Literal["default", "client"]

# Voxel indices are packed into one int64 key with 21 bits per axis: a lattice of +-2^20 voxels
# per axis around the fixed origin, which is "unbounded" for any capture.
KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)

# The analytic opacity logit's intercept without an explicit `DecoderSettings.opacity_bias`: with
# depth denoising on, weakly supported voxels are mostly real surface and the line starts at 0; with
# it off, rough depth leaves scattered voxels that a negative intercept keeps see-through.
BIAS_WITH_DENOISING = 0.0
BIAS_WITHOUT_DENOISING = -3.0


def error_message(exc: ValidationError, prefix: str) -> str:
    """The first error of ``exc`` as ``"path: problem, got value"`` (path joined with dots)."""
    first = exc.errors()[0]
    path = ".".join([prefix, *map(str, first["loc"])] if prefix else map(str, first["loc"]))
    msg = first["msg"]
    if first["type"] == "value_error":  # a model validator's own "field: problem" message
        return msg.removeprefix("Value error, ")
    if first["type"] == "extra_forbidden":
        moved = FLAT_NAMES.get(path)
        return f"{path}: unknown setting" + (f" (it is {moved} now)" if moved else "")
    return f"{path}: {msg[:1].lower()}{msg[1:]}, got {first['input']!r}"


class _NamedErrors(type(BaseModel)):
    """Construction raises a ValueError ``"path: problem"`` instead of pydantic's multi-line report.
    On the metaclass, not in ``__init__``: a model with its own ``__init__`` is validated through it
    when nested, which would fold a group's field errors into one error on the group."""

    def __call__(cls, *args: Any, **kwargs: Any):
        try:
            return super().__call__(*args, **kwargs)
        except ValidationError as exc:
            raise ValueError(error_message(exc, cls._path)) from None


class SettingsGroup(BaseModel, metaclass=_NamedErrors):
    """Frozen (hashable), strict, closed: an unknown name or a wrongly typed value is an error."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False,
                              validate_default=True, use_attribute_docstrings=True)
    _path: ClassVar[str] = ""  # where the group sits in SceneConfig, to name its fields in errors

    def to_dict(self) -> dict:
        return self.model_dump()


NonNegative = Annotated[float, Field(ge=0)]
Positive = Annotated[float, Field(gt=0)]
# A length of the sensor model, metres: beyond 10 m of depth noise no depth is worth folding.
SensorLength = Annotated[float, Field(ge=0, le=10.0)]
# Depths and voxels live on the lattice of KEY_BITS-bit indices; these bounds keep a session on it.
MIN_VOXEL, MAX_VOXEL, MAX_DEPTH = 1e-5, 100.0, 1e5
# rows are indexed with int32 in the hash table (and 300 bytes a voxel make 2^31 voxels absurd anyway)
MAX_VOXELS = 2**31 - 1


class DepthRange(SettingsGroup):
    """The depths accepted from frames, metres; pixels outside are ignored."""

    _path: ClassVar[str] = "range"

    near: NonNegative = 0.05
    """Nearest depth accepted from frames, metres; nearer pixels are ignored."""
    far: Annotated[float, Field(gt=0, le=MAX_DEPTH)] = 20.0
    """Farthest depth accepted from frames, metres; farther pixels are ignored. It must stay on the
    voxel lattice: at most 2^20 voxels from the origin (checked by `SceneConfig`)."""

    @model_validator(mode="after")
    def _ordered(self) -> "DepthRange":
        if self.near >= self.far:
            raise ValueError(f"range.near: must be below range.far ({self.near} >= {self.far})")
        return self


class FeatureSettings(SettingsGroup):
    """The per-pixel features that are fused (F_view, F_scene)."""

    _path: ClassVar[str] = "features"

    backend: FeatureBackend = "default"
    """``default`` (the training-free extractor) or ``client`` (``Frame.features``, resized to the
    image and projected to ``dim`` channels)."""
    dim: Annotated[int, Field(ge=1, le=512)] = 16
    """L, channels of the fused features."""
    client_channels: Annotated[int | None, Field(ge=1, le=512)] = None
    """With ``backend`` ``client``: the channels a pixel of every frame's features carries (each
    count is projected to ``dim`` its own way, so a frame with another count would mix unrelated
    channels in). None: the first frame's (`scene.choices`), fixed for the session's life."""


class ColourSolve(SettingsGroup):
    """The render-consistent colour solve: kept input views, and Gaussian colours solved so that
    renders reproduce them."""

    _path: ClassVar[str] = "colour_solve"

    views: Annotated[int, Field(ge=0, le=64)] = 16
    """Keep this many input views (colour and camera, spread over the stream: `scene.keyframes`) and
    solve the decoded Gaussians' colours (SH up to degree 1) so that renders reproduce them
    (`decode.solve_colours`); geometry and opacity unchanged. 0 turns it off. A decode that solves
    takes seconds instead of milliseconds (``refresh`` says which decodes do); the service solves
    off its renders instead, whenever a session has no frame waiting (`Scene.solve_colours`)."""
    refresh: Annotated[int, Field(ge=1, le=1_000_000)] = 4
    """Frames folded between two colour solves of a streaming scene. The first decode solves from
    scratch; later decodes reuse the last solution (its offsets, on the voxels it solved: voxels
    decoded since keep their fused colours) until this many frames were folded since, and then
    solve again in a few steps, starting from it (`decode.colour_offsets`)."""
    scale: Annotated[float, Field(gt=0, le=1)] = 0.5
    """Size of the kept views relative to the input (0.5: a quarter of the pixels, of the solve's
    time and of the views' memory)."""


class SensorNoise(SettingsGroup):
    """Noise model of supplied depth that carries no per-pixel std: sigma(z) = sigma0 + sigma2
    (z - sigma_ref)^2 metres, plus ``edge_weight`` times the pixel's largest depth jump to a valid
    8-neighbour. ``family`` names the sensor family whose preset (`config.sensors`) gives every value
    left None; a value set here overrides the preset's. ``weight_floor``: how far below its
    voxel's best the weight of an observation may fall."""

    _path: ClassVar[str] = "sensor"

    family: SensorFamily = "auto"
    """The depth sensor's family: ``structured_light`` (Kinect v1, Xtion, PrimeSense), ``active_stereo``
    (RealSense D4xx), ``time_of_flight`` (Kinect v2, Azure Kinect), ``phone_lidar`` (iPhone / iPad
    LiDAR), ``hololens`` (HoloLens 2 depth), or ``auto``: detected from the first frame's depth where
    its quantisation shows the family, else the default family (`scene.choices`); the fold report
    says which and why. Fixed for the scene's life once chosen."""
    sigma0: SensorLength | None = None
    """Constant term of the depth std, metres (None: the family's preset)."""
    sigma2: SensorLength | None = None
    """Quadratic term of the depth std, metres per square metre of distance from ``sigma_ref`` (None:
    the family's preset)."""
    sigma_ref: Annotated[float, Field(ge=0, le=MAX_DEPTH)] | None = None
    """Depth at which the std is smallest, metres (None: the family's preset)."""
    edge_weight: Annotated[float, Field(ge=0, le=100.0)] | None = None
    """Weight of the largest neighbour depth jump added to the std, so "flying pixels" on depth
    discontinuities get low reliability (None: the family's preset)."""
    registration_px: Annotated[float, Field(ge=0, le=32)] | None = None
    """Pixels; evidence within this distance of a depth edge is down-weighted (its reliability times
    min(1, (d + 1) / (registration_px + 1)), d the distance), because colour and depth measured by
    two sensors disagree there and the colour may belong to the surface behind
    (`evidence.registration`). 0 turns it off (None: the family's preset)."""
    weight_floor: Annotated[float, Field(ge=0, le=1)] = 0.5
    """The least weight an observation gets in its voxel's sums, as a share of the voxel's most
    reliable observation's. The reliability and similarity weights model depth noise and
    appearance, not misregistration at edges, quantised far depth or exposure, where observations
    disagree for other reasons and a plain average does better; the floor keeps every observation in
    the average. 1 weighs them all alike (the ``average`` rule), 0 is the paper's rule. Chosen
    leave-one-capture-out (`eval.tuning`); settings stored before it existed read as 0, the rule
    their scenes were folded with (`SceneConfig.from_dict`)."""

    @property
    def chosen(self) -> bool:
        """Whether the family and every value are known (`with_preset` made them so)."""
        return self.family != "auto" and None not in self.model_dump().values()

    def with_preset(self, family: str | None = None) -> "SensorNoise":
        """Every value left None taken from the preset of ``family`` (default: this group's own,
        which must then not be ``auto``); values set here stay (they take precedence)."""
        family = self.family if family is None else family
        preset = SENSOR_PRESETS[family]  # KeyError for "auto": the caller chooses a family first
        return SensorNoise(**{**preset, **{k: v for k, v in self.model_dump().items() if v is not None},
                              "family": family})

    def in_effect(self, depth) -> "SensorNoise":
        """This group where it is `chosen`, else `with_preset` of the family ``depth`` ([H, W] metres,
        or None) shows (`detect_family`): what evidence from that depth uses outside a scene, which
        chooses once for its life (`scene.choices`)."""
        return self if self.chosen else self.with_preset(None if self.family != "auto" else detect_family(depth)[0])


class FreeSpace(SettingsGroup):
    """Free-space ("seen-through") evidence: rays that pass a voxel and end on a surface behind it
    count against the voxel when decoding."""

    _path: ClassVar[str] = "free_space"

    enabled: bool = True
    """Fold free-space evidence and use it in decoding."""
    margin: NonNegative = 0.0
    """A voxel is seen through by a ray whose surface lies more than margin * voxel_size +
    sigmas * sigma(depth) behind the voxel's centre (margin in voxels). 0: the distance is the
    sensor's noise at that depth alone, which holds across sensors and voxel sizes
    (leave-one-capture-out, `eval.tuning`)."""
    sigmas: NonNegative = 3.0
    """The depth-std part of that distance, in standard deviations of the ray's depth."""
    cell: Annotated[int, Field(ge=1, le=64)] = 8
    """Pixels per side of the cells of a frame's coarse see-through map."""
    history: Annotated[int, Field(ge=1, le=100_000)] = 64
    """Frames whose see-through maps are kept, so voxels created later still get their evidence."""
    dominance: NonNegative = 2.0
    """Decoding drops voxels whose free-space evidence exceeds this multiple of their support
    R_scene. Above 1 because the see-through weight counts rays as if the voxel faced the camera,
    which overstates it up to twice for surfaces seen at 60 degrees."""


class DepthEstimation(SettingsGroup):
    """The depth front end: plane sweep for frames without depth (and for depth completion), and
    the median denoising of rough supplied depth."""

    _path: ClassVar[str] = "depth"

    sources: Annotated[int, Field(ge=1, le=8)] = 2
    """Source views a frame without depth is swept against."""
    hypotheses: Annotated[int, Field(ge=2, le=512)] = 64
    """K, depth hypotheses of the sweep, uniform in inverse depth between near and far."""
    source_window: Annotated[int, Field(ge=1, le=64)] = 4
    """Recent views kept as sweep sources (and frames without depth that may wait for a partner at
    once)."""
    completion: bool = False
    """Also sweep frames that carry depth, and fill the large holes of their depth (beyond
    ``completion_radius`` pixels from any measured pixel: beyond the sensor's range or field of
    view, dark or specular surfaces) with the swept depth. Measured pixels are never changed; a frame
    without holes is not swept. Buys coverage at some cost in accuracy on the covered pixels."""
    completion_radius: Annotated[int, Field(ge=1, le=256)] = 6
    """Pixels; with ``completion``, holes closer than this to a measured pixel stay unfilled."""
    denoise_radius: Annotated[int, Field(ge=0, le=32)] = 7
    """Pixels; a frame whose depth is far rougher than its noise model gets the median of a
    (2 radius + 1)^2 window instead, with that median's std (`evidence.denoise`). Clean sensor depth
    is never touched; 0 turns it off."""


class DecoderSettings(SettingsGroup):
    """The analytic (untrained) decoder of a new scene. A loaded snapshot keeps its decoder's own
    parameters."""

    _path: ClassVar[str] = "decoder"

    opacity_slope: Positive = 3.0
    """a of the opacity logit a r + b, r in [0, 1) being support in typical views (`decode.decoder`):
    a fully supported surface is sigmoid(a + b) opaque (95 % at the default), a weakly supported one
    (depth edges, thin or sparse geometry) about half. Chosen across captures (`eval.tuning`):
    steeper lines draw weak evidence as solid as strong."""
    opacity_bias: Annotated[float, Field(allow_inf_nan=False)] | None = None
    """b of the same line, the logit of a voxel without reliable support. None (default) follows the
    depth denoising: 0 with it on, -3 with it off, where noisy depth leaves scattered voxels that
    should stay see-through (`SceneConfig.opacity_bias`)."""
    sh_regularization: NonNegative = 0.003
    """Ridge weight, relative to R_scene, pulling the SH fit's higher coefficients toward zero (the DC
    colour) where few view directions were seen. A degree-1 term keeps var / (var + ridge) of its
    least-squares value, var being the weighted variance of its basis over the observations
    (C1^2 theta^2 / 4 for two views theta radians apart): small enough to trust views some
    20 degrees apart, large enough to ignore the spread of rays within one view."""


class Research(SettingsGroup):
    """Ablation switches of the aggregation rule, for the evaluation's method definitions
    (`eval.methods`); not part of the public (HTTP, CLI) settings."""

    _path: ClassVar[str] = "research"

    weighting: Weighting = "full"
    """The aggregation rule: ``full`` is the method's rule; ``no_reliability`` and ``average`` treat
    every reliability as 1 (in the free-space evidence too); ``no_similarity`` and ``average`` drop
    the cosine factor."""
    eps: Positive = 1e-8
    """The epsilon of F_scene = sum W F / (R_scene + eps)."""


class SceneConfig(SettingsGroup):
    """Settings of a scene: what a user chooses at the top level, expert tuning in groups.

    Groups accept a mapping or an instance: ``SceneConfig(voxel_size=0.01, depth={"sources": 3})``.
    """

    voxel_size: Annotated[float, Field(ge=MIN_VOXEL, le=MAX_VOXEL)] | None = None
    """Edge length of the sparse lattice's voxels, in the scene's unit (metres). ``range.far`` must
    stay on the lattice: at most 2^20 voxels from the origin. None: chosen from the first frame with
    depth (6 pixel footprints at its median depth, `scene.choices`) and fixed for the scene's life."""
    max_voxels: Annotated[int, Field(gt=0, le=MAX_VOXELS)] | None = None
    """Cap on the number of voxels (None = unbounded); a fold that would exceed it raises instead of
    folding part of a frame."""
    sh_degree: Annotated[int, Field(ge=0, le=3)] = 1
    """Degree of the per-voxel spherical-harmonics colour fit (0 = view-independent colour)."""
    range: DepthRange = DepthRange()
    """The depths accepted from frames."""
    features: FeatureSettings = FeatureSettings()
    """The fused features: where they come from and how many channels."""
    colour_solve: ColourSolve = ColourSolve()
    """The render-consistent colour solve (on by default: 16 kept views)."""
    model: Annotated[str, Field(min_length=1, max_length=4096)] = "default"
    """The decoder's parameters: ``default`` (the checkpoint shipped with the library when one ships,
    else the training-free decoder), ``none`` (the training-free, analytic decoder) or the path of a
    ``.safetensors`` checkpoint written by ``canonical train`` (`decode.checkpoint`). A snapshot keeps
    the parameters it was decoded with, so a restored scene decodes the same without the file."""
    sensor: SensorNoise = SensorNoise()
    """The depth sensor's noise model."""
    free_space: FreeSpace = FreeSpace()
    """Free-space evidence."""
    depth: DepthEstimation = DepthEstimation()
    """The depth front end (plane sweep, completion, denoising)."""
    decoder: DecoderSettings = DecoderSettings()
    """The analytic decoder of a new scene."""
    research: Research = Research()
    """Ablations, for the evaluation only."""

    @field_validator("model")
    @classmethod
    def _model_name(cls, value: str) -> str:
        if value not in ("default", "none") and not value.endswith(".safetensors"):
            raise ValueError(f"model: expected 'default', 'none' or the path of a .safetensors checkpoint, got {value!r}")
        return value

    @model_validator(mode="after")
    def _far_on_lattice(self) -> "SceneConfig":
        far = self.range.far
        if self.voxel_size is not None and far > self.voxel_size * KEY_OFFSET:
            raise ValueError(f"range.far: {far} is {far / self.voxel_size:.3g} voxels of {self.voxel_size}, beyond the "
                             f"lattice's {KEY_OFFSET} voxels from the origin; use larger voxels or a nearer far")
        return self

    @property
    def chosen(self) -> bool:
        """Whether nothing is left to choose from the first frame (`scene.choices`): the voxel size is
        set, the sensor's family and values are known, and so are client features' channels."""
        return self.voxel_size is not None and self.sensor.chosen and (
            self.features.backend != "client" or self.features.client_channels is not None)

    @property
    def uses_reliability(self) -> bool:
        """Whether the weighting uses R_view (else every reliability counts as 1)."""
        return self.research.weighting in ("full", "no_similarity")

    @property
    def uses_similarity(self) -> bool:
        """Whether W carries the factor max(0, cos(F, F_rep))."""
        return self.research.weighting in ("full", "no_reliability")

    @property
    def opacity_bias(self) -> float:
        """The decoder's opacity intercept: ``decoder.opacity_bias``, or, when that is None, the one
        that suits the depth denoising setting."""
        if self.decoder.opacity_bias is not None:
            return self.decoder.opacity_bias
        return BIAS_WITH_DENOISING if self.depth.denoise_radius > 0 else BIAS_WITHOUT_DENOISING

    def replace(self, **changes: Any) -> "SceneConfig":
        """A validated copy with ``changes``; a group given as a mapping changes only the fields it
        names: ``config.replace(free_space={"enabled": False})``."""
        merged = self.to_dict()
        for name, value in changes.items():
            merged[name] = {**merged[name], **value} if isinstance(value, dict) and isinstance(merged.get(name), dict) \
                else value
        return type(self)(**merged)

    @classmethod
    def from_dict(cls, d: dict) -> "SceneConfig":
        """The inverse of `to_dict`; also reads the flat layout of earlier snapshots and session
        files (every setting at the top level, see `FLAT_NAMES`), and settings written before
        ``sensor.weight_floor`` existed with the floor 0 they were folded with."""
        if not isinstance(d, dict):
            raise ValueError(f"config: expected a mapping of settings, got {type(d).__name__}")
        settings = migrate_flat(d)
        if isinstance(settings.get("sensor", {}), dict):  # stored before the weight floor: folded without one
            settings["sensor"] = {"weight_floor": 0.0, **settings.get("sensor", {})}
        return cls(**settings)
