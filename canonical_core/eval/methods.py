"""The methods under evaluation: each builds a renderable model from input frames.

``METHODS`` maps a name to a `Method`:
- ``canonical``: the full method, `Scene` with the paper's weighting and the library's defaults,
  decoded analytically and its colours solved against the inputs (`SceneConfig.colour_solve`, on
  by default; ``canonical:colour_solve.views=0`` is the fused colours alone);
- ``no_reliability``, ``no_similarity``, ``average``: the aggregation ablations (``SceneConfig.research``,
  which only the evaluation sets);
- ``plain_decoding``: the same fused voxels as ``canonical``, but every Gaussian gets one opacity,
  the analytic head's value at full support (no reliability-conditioned opacity);
- ``no_free_space``, ``no_view_dependence``: without free-space evidence / with SH degree 0;
- ``depth_completion``: ``canonical`` with `SceneConfig.depth.completion` (large sensor-depth holes
  filled by the plane sweep against the session's earlier views);
- ``colour_solve``: ``canonical`` with `SceneConfig.colour_solve.views` 16 (every input of the
  protocol kept, the default): decoded colours solved so that renders reproduce the input views
  (least squares), whatever the default;
- ``completion_solve``: both of the above, the setting for sessions captured first and viewed after;
- ``pixel_aligned``, ``gaussian_merge``: baselines without fusion (see `baselines`);
- ``open3d_tsdf``: Open3D TSDF fusion + ray-cast colour (needs the ``bench`` extra).

Example:
    >>> from canonical_core.datasets import synthetic_rgbd
    >>> frames = list(synthetic_rgbd(num_frames=2, width=64, height=48))
    >>> model, ms = build("canonical", frames, voxel_size=0.02)
    >>> view = model.render(frames[0].camera)
    >>> view.rgb.shape, model.gaussians > 0
    (torch.Size([48, 64, 3]), True)
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import torch
from torch import Tensor

from ..camera import Camera
from ..frame import Frame
from ..gaussians import Gaussians
from ..rendering import Colour, render
from ..scene import Scene, SceneConfig
from ..config import Weighting, parse_setting
from .baselines import full_support_opacity, gaussian_merge, pixel_aligned
from .open3d_tsdf import Open3DTSDF, open3d_import_error


@dataclass
class View:
    """What a method shows at a camera."""

    rgb: Tensor  # [H, W, 3] in [0, 1], black where nothing is drawn (`rendering.render`'s colour modes)
    alpha: Tensor  # [H, W] in [0, 1], accumulated opacity (1 / 0 for a ray cast hit / miss)
    depth: Tensor | None = None  # [H, W] z-depth, 0 where nothing is drawn (with rgb)
    features: Tensor | None = None  # [H, W, C] feature splat, when requested (instead of rgb and depth)


class Model(Protocol):
    @property
    def gaussians(self) -> int | None: ...  # None for models that are not Gaussians

    def render(self, camera: Camera, features: bool = False, colour: Colour = "normalised") -> View: ...


@dataclass
class SplatModel:
    """Gaussians, rendered with `canonical_core.rendering.render` on a black background; depth is
    the median depth (the surface that covers most of a pixel), as the service renders it."""

    splats: Gaussians

    @property
    def gaussians(self) -> int:
        return len(self.splats)

    def render(self, camera: Camera, features: bool = False, colour: Colour = "normalised") -> View:
        out = render(self.splats, camera, outputs=("features", "alpha") if features else ("rgb", "depth", "alpha"),
                     colour=colour, depth_mode="median")
        return View(rgb=out.rgb, alpha=out.alpha, depth=out.depth, features=out.features)


@dataclass
class TSDFModel:
    """The Open3D peer, rendered by ray casting: a hit pixel shows its surface's colour in full, so
    both colour modes give the same image."""

    tsdf: Open3DTSDF

    @property
    def gaussians(self) -> None:
        return None

    def render(self, camera: Camera, features: bool = False, colour: Colour = "normalised") -> View:
        if features:
            raise ValueError("features: the open3d_tsdf peer carries no features")
        rgb, depth = self.tsdf.ray_cast(camera)
        return View(rgb=rgb, alpha=(depth > 0).float(), depth=depth)


# (input frames, voxel size, whether feature splats are needed) -> model
Builder = Callable[[Sequence[Frame], float, bool], Model]


@dataclass(frozen=True)
class Method:
    """A method: its builder, whether it can splat features, and why it cannot run here (if so)."""

    build: Builder
    features: bool
    unavailable: Callable[[], str | None] = lambda: None


@dataclass(frozen=True)
class SceneBuilder:
    """A `Scene` method's builder: aggregation rule ``weighting`` and other `SceneConfig` settings
    (groups as dicts), kept as data so that `configured` can add settings to it."""

    weighting: Weighting
    uniform_opacity: bool = False
    settings: Mapping[str, Any] = field(default_factory=dict)

    def __call__(self, frames: Sequence[Frame], voxel_size: float, features: bool) -> Model:
        scene = Scene(SceneConfig(voxel_size=voxel_size, research={"weighting": self.weighting}, **self.settings))
        for frame in frames:
            scene.fold(frame)
        splats = scene.decode()
        if self.uniform_opacity:
            splats = replace(splats, opacities=torch.full_like(splats.opacities, full_support_opacity(scene.decoder)))
        return SplatModel(splats)


def _scene(weighting: Weighting, uniform_opacity: bool = False, **settings) -> Builder:
    """A `Scene` method: aggregation rule ``weighting`` and other `SceneConfig` settings (groups as dicts)."""
    return SceneBuilder(weighting, uniform_opacity, settings)


def _splats(make: Callable[[Sequence[Frame], float, bool], Gaussians]) -> Builder:
    return lambda frames, voxel_size, features: SplatModel(make(frames, voxel_size, features))


def _tsdf(frames: Sequence[Frame], voxel_size: float, features: bool) -> Model:
    # rays stop past the farthest input depth (plus the truncation band)
    depth_max = max(float(f.depth.max()) for f in frames) + 8 * voxel_size
    tsdf = Open3DTSDF(voxel_size, depth_max=depth_max, block_count=1024)
    for frame in frames:
        tsdf.integrate(frame)
    return TSDFModel(tsdf)


def _open3d_missing() -> str | None:
    error = open3d_import_error()
    return None if error is None else (f"needs Open3D (pip install 'canonicalgs-fusion[bench]'; on Debian also "
                                       f"apt-get install libusb-1.0-0): {error}")


METHODS: dict[str, Method] = {
    "canonical": Method(_scene("full"), features=True),
    "no_reliability": Method(_scene("no_reliability"), features=True),
    "no_similarity": Method(_scene("no_similarity"), features=True),
    "average": Method(_scene("average"), features=True),
    "plain_decoding": Method(_scene("full", uniform_opacity=True), features=True),
    "no_free_space": Method(_scene("full", free_space={"enabled": False}), features=True),
    "no_view_dependence": Method(_scene("full", sh_degree=0), features=True),
    "depth_completion": Method(_scene("full", depth={"completion": True}), features=True),
    "colour_solve": Method(_scene("full", colour_solve={"views": 16}), features=True),
    "completion_solve": Method(_scene("full", depth={"completion": True}, colour_solve={"views": 16}), features=True),
    "pixel_aligned": Method(_splats(pixel_aligned), features=True),
    "gaussian_merge": Method(_splats(gaussian_merge), features=True),
    "open3d_tsdf": Method(_tsdf, features=False, unavailable=_open3d_missing),
}


def check_methods(names: Sequence[str]) -> list[str]:
    """Validate method specs (`parse_method`: a name, or a Scene method's name with settings);
    returns their labels, order kept and duplicates dropped."""
    if isinstance(names, str) or not names:
        raise ValueError(f"methods: expected a non-empty list of names from {list(METHODS)}, got {names!r}")
    return list(dict.fromkeys(parse_method(name).label for name in names))


def _nested(settings: Mapping[str, Any]) -> dict:
    """Dotted setting paths (``free_space.margin``) as nested dicts (``{"free_space": {"margin": ...}}``)."""
    out: dict = {}
    for path, value in settings.items():
        *groups, leaf = path.split(".")
        node = out
        for g in groups:
            node = node.setdefault(g, {})
        node[leaf] = value
    return out


def _merged(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict:
    out = dict(base)
    for key, value in extra.items():
        out[key] = _merged(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), Mapping) else value
    return out


def configured(name: str, settings: Mapping[str, Any]) -> Method:
    """Method ``name`` with extra `SceneConfig` settings on top of its own, e.g. ``{"sh_degree": 0}``
    or a decoder checkpoint; paths may be dotted (``free_space.margin``), values as
    `parse_setting` reads them. Only `Scene` methods take settings (ValueError naming ``methods``
    otherwise); the settings are checked when the method builds its scene.

    Example:
        >>> configured("average", {"sh_degree": 0}).build.settings
        {'sh_degree': 0}
    """
    if name not in METHODS:
        raise ValueError(f"methods: unknown method {name!r}; expected some of {list(METHODS)}")
    method = METHODS[name]
    if not settings:
        return method
    if not isinstance(method.build, SceneBuilder):
        raise ValueError(f"methods: {name} builds no Scene and takes no settings (got {dict(settings)!r})")
    if "voxel_size" in settings:  # what the run gives every method alike
        raise ValueError(f"methods: {name}:voxel_size is the run's, the same for every method (--voxel-size)")
    builder = replace(method.build, settings=_merged(method.build.settings, _nested(settings)))
    return replace(method, build=builder)


@dataclass(frozen=True)
class MethodSpec:
    """A method to run: its name in `METHODS` and extra `SceneConfig` settings (dotted paths)."""

    name: str
    settings: Mapping[str, Any]

    @property
    def label(self) -> str:
        """How results name it: ``NAME`` or ``NAME:SETTING=VALUE[:...]``."""
        return ":".join([self.name, *(f"{k}={v}" for k, v in self.settings.items())])

    def method(self, extra: Mapping[str, Any] | None = None) -> Method:
        return configured(self.name, {**self.settings, **(extra or {})})


def parse_method(text: str) -> MethodSpec:
    """``NAME`` or ``NAME:SETTING=VALUE[:SETTING=VALUE...]`` (settings as `parse_setting` reads
    them, e.g. ``canonical:model=ckpt.safetensors``) -> `MethodSpec`; ValueError naming ``methods``
    or the setting for a bad one. Only `Scene` methods take settings.

    Example:
        >>> parse_method("canonical:sh_degree=0").settings, parse_method("average").label
        ({'sh_degree': 0}, 'average')
    """
    if not isinstance(text, str):
        raise ValueError(f"methods: expected a method name, got {text!r}")
    name, *parts = text.strip().split(":")
    spec = MethodSpec(name, dict(parse_setting(p) for p in parts))
    spec.method()  # checks the name, and that only Scene methods take settings
    return spec


def build(spec: str, frames: Sequence[Frame], voxel_size: float, features: bool = False) -> tuple[Model, float]:
    """Build method ``spec`` (`parse_method`: a name, or a Scene method with settings) from
    ``frames``; returns the model and the wall time in ms (for the scene methods: fold of every
    frame + decode)."""
    method = parse_method(spec).method()
    t0 = time.perf_counter()
    model = method.build(frames, voxel_size, features)
    return model, (time.perf_counter() - t0) * 1000.0
