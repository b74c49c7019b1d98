"""``render``: one entry point for rasterizing Gaussians at a camera, on any backend."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Sequence, get_args

import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from ..gaussians.container import GEOMETRY, check_finite
from .gsplat_backend import composite_gsplat, gsplat_available
from .cpu_tiles import render_cpu
from .projection import Blend, Channel, project_splats
from .reference import composite_reference

Output = Literal["rgb", "depth", "alpha", "features", "labels"]
Backend = Literal["auto", "reference", "cpu", "gsplat"]
Colour = Literal["composited", "normalised"]
DepthMode = Literal["median", "expected"]


@dataclass
class RenderResult:
    """Rendered maps; a field is None unless it was requested in ``outputs``.

    Attributes:
        rgb: [H, W, 3] colour in [0, 1]: with ``colour="composited"`` sum(w_i c_i) + T_final *
            background (3DGS); with ``"normalised"`` sum(w_i c_i) / sum(w_i), the background only
            where nothing is drawn.
        depth: [H, W] view-space depth (``depth_mode``); 0 where alpha is 0.
        alpha: [H, W] accumulated opacity, 1 - final transmittance.
        features: [H, W, C] composited features sum(w_i f_i) (no background, not normalised).
        labels: [H, W] int64 argmax of the composited label scores; -1 where alpha is 0, and where
            under half the pixel's weight comes from Gaussians with label evidence (surfaces that only
            unlabelled pixels saw: a class map's negative ids, frames without labels).
    """

    rgb: Tensor | None = None  # [H, W, 3]
    depth: Tensor | None = None  # [H, W]
    alpha: Tensor | None = None  # [H, W]
    features: Tensor | None = None  # [H, W, C]
    labels: Tensor | None = None  # [H, W] int64

    def __repr__(self) -> str:  # the maps' shapes, not their pixels
        shown = (f"{name}={list(t.shape)}" for name, t in vars(self).items() if t is not None)
        return f"RenderResult({', '.join(shown)})"


def _check_outputs(outputs: Sequence[str], gaussians: Gaussians) -> tuple[str, ...]:
    if isinstance(outputs, str) or not outputs:
        raise ValueError(f"outputs: expected a non-empty sequence of {list(get_args(Output))}, got {outputs!r}")
    for name in outputs:
        if name not in get_args(Output):
            raise ValueError(f"outputs: unknown output {name!r}; expected some of {list(get_args(Output))}")
        if name in ("features", "labels") and getattr(gaussians, name) is None:
            raise ValueError(f"{name}: requested in outputs, but the Gaussians carry no {name}")
    return tuple(dict.fromkeys(outputs))


def _background(background) -> Tensor:  # [3] float64
    if background is None:
        return torch.zeros(3, dtype=torch.float64)
    try:
        background = torch.as_tensor(background, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"background: expected an rgb colour of 3 numbers, got {background!r}") from None
    if background.shape != (3,):
        raise ValueError(f"background: expected an rgb colour of shape [3], got {list(background.shape)}")
    if not torch.isfinite(background).all():  # NaN or inf would reach every pixel the Gaussians leave uncovered
        raise ValueError(f"background: expected finite values, got {background.tolist()}")
    return background



def _channel_width(gaussians: Gaussians, channel: Channel) -> int:  # columns in `channel_values`
    return 3 if channel == "rgb" else getattr(gaussians, channel).shape[1] + (channel == "labels")


def _resolve_backend(backend: str, device: torch.device, median_depth: bool) -> str:
    """The backend to run; ``median_depth``: a median depth map is asked for, which gsplat does not
    compute (``auto`` then takes the cpu backend)."""
    if backend not in get_args(Backend):
        raise ValueError(f"backend: expected one of {list(get_args(Backend))}, got {backend!r}")
    if backend == "auto":
        return "gsplat" if device.type == "cuda" and gsplat_available() and not median_depth else "cpu"
    if backend == "gsplat" and not (device.type == "cuda" and gsplat_available()):
        raise ValueError(f"backend: 'gsplat' needs the gsplat package and CUDA tensors (Gaussians are on {device})")
    if backend == "gsplat" and median_depth:
        raise ValueError("depth_mode: 'median' is computed by the cpu and reference backends, not by gsplat; "
                         "ask for 'expected' depth or another backend")
    return backend


def blend_rgb(
    blend: Blend,  # values [H, W, 3]: the RGB sums
    colour: Colour = "composited",
    background: Tensor | Sequence[float] | None = None,  # [3] rgb, default black
) -> Tensor:  # [H, W, 3] in [0, 1]
    """The image `render` shows from an RGB blend: in ``"normalised"`` colour the sums over their
    weight (the background where nothing was drawn), in ``"composited"`` colour the sums over the
    background; clamped to [0, 1]."""
    background = _background(background).to(blend.values)
    if colour == "normalised":
        covered = blend.weight_sums > 0
        safe_weights = torch.where(covered, blend.weight_sums, torch.ones_like(blend.weight_sums))
        rgb = torch.where(covered[..., None], blend.values / safe_weights[..., None], background)
    else:
        rgb = blend.values + blend.transmittance[..., None] * background
    return rgb.clamp(0.0, 1.0)


def render(
    gaussians: Gaussians,
    camera: Camera,
    outputs: Sequence[Output] = ("rgb", "depth", "alpha"),
    background: Tensor | Sequence[float] | None = None,  # [3] rgb, default black
    colour: Colour = "composited",
    depth_mode: DepthMode = "expected",
    backend: Backend = "auto",
    near_plane: float = 0.01,
    num_threads: int | None = None,
) -> RenderResult:
    """Rasterize 3D Gaussians at ``camera`` by front-to-back alpha compositing (3DGS).

    The image model (EWA projection, 0.3 px^2 low-pass, 3-sigma support, 1/255 and 1e-4 cut-offs)
    is documented in ``canonical_core.rendering.splat_geometry``.

    Args:
        gaussians: N Gaussians; ``features`` / ``labels`` must be present to render them.
        camera: pinhole camera (OpenCV axes, pixel (u, v) centred at (u, v)); sets H and W.
        outputs: which maps to compute, any of "rgb", "depth", "alpha", "features", "labels".
            RGB, features and labels are composited in the same pass.
        background: rgb colour behind the Gaussians, composited as rgb + T_final * background.
        colour: "composited" (3DGS: each pixel's colour is the blend of its splats over the
            background) or "normalised": the blend divided by its accumulated weight, the expected
            colour of the surface the ray hits, as ``depth`` is its expected depth. Where splats do
            not tile a surface edge to edge (gaps between sparse splats, a surface seen from a new
            angle) the composited blend darkens toward the background; the normalised one keeps the
            surface's colour, as surface splatting normalises by the sum of its kernels. ``alpha``
            still says how much of the pixel is covered.
        depth_mode: "expected": sum(w_i z_i) / sum(w_i), the blend of every splat on the ray;
            "median": the depth of the splat at which the pixel's transmittance first falls below
            1/2, i.e. the surface that covers most of the pixel, and the expected depth where the
            pixel stays more than half transparent. The expected depth mixes surfaces where a ray
            grazes an edge or meets a semi-transparent one (a foreground edge over the background
            reads as a depth between them); the median depth does not. gsplat computes only the
            expected depth ("auto" renders median depth on the cpu backend).
        backend: "reference" (PyTorch, differentiable, O(splats x pixels) per tile), "cpu"
            (fast: numba projection and a vectorised C compositor, float32, no autograd), "gsplat"
            (CUDA) or "auto" (gsplat for CUDA tensors when it is installed, else cpu).
        near_plane: Gaussians whose mean is closer than this view-space depth are culled.
        num_threads: CPU threads for the cpu backend (default ``torch.get_num_threads()``).

    Returns:
        RenderResult with the requested maps on the Gaussians' device, each [H, W] or [H, W, C].

    Raises:
        ValueError: unknown output, colour mode, depth mode or backend, features/labels requested but
            absent, a background that is not [3], a non-positive near plane or thread count, median
            depth asked of gsplat.
    """
    if not isinstance(gaussians, Gaussians):
        raise ValueError(f"gaussians: expected Gaussians, got {type(gaussians).__name__}")
    if not isinstance(camera, Camera):
        raise ValueError(f"camera: expected a Camera, got {type(camera).__name__}")
    outputs = _check_outputs(outputs, gaussians)
    check_finite(gaussians, (*GEOMETRY, "sh", *(c for c in ("features", "labels") if c in outputs)))
    background = _background(background)
    if colour not in get_args(Colour):
        raise ValueError(f"colour: expected one of {list(get_args(Colour))}, got {colour!r}")
    if depth_mode not in get_args(DepthMode):
        raise ValueError(f"depth_mode: expected one of {list(get_args(DepthMode))}, got {depth_mode!r}")
    if not 0 < near_plane < math.inf:  # an infinite plane would cull every Gaussian, silently
        raise ValueError(f"near_plane: expected a positive, finite distance, got {near_plane!r}")
    num_threads = torch.get_num_threads() if num_threads is None else num_threads
    if isinstance(num_threads, bool) or not isinstance(num_threads, int) or num_threads < 1:
        raise ValueError(f"num_threads: expected a positive integer, got {num_threads!r}")
    device = gaussians.means.device
    median_depth = "depth" in outputs and depth_mode == "median"
    backend = _resolve_backend(backend, device, median_depth)
    channels: tuple[Channel, ...] = tuple(c for c in ("rgb", "features", "labels") if c in outputs)

    if backend == "gsplat":
        blend = composite_gsplat(gaussians, camera, channels, near_plane)
    elif backend == "reference":
        splats = project_splats(gaussians, camera, channels, near_plane)
        blend = composite_reference(splats, camera.width, camera.height)
    else:
        blend = Blend(*(None if t is None else t.to(device)
                        for t in render_cpu(gaussians, camera, channels, near_plane, num_threads, median_depth=median_depth)))

    alpha = 1 - blend.transmittance
    covered = blend.weight_sums > 0
    result = RenderResult()
    widths = [_channel_width(gaussians, c) for c in channels]
    split = dict(zip(channels, blend.values.split(widths, -1))) if channels else {}
    if "rgb" in outputs:
        result.rgb = blend_rgb(blend._replace(values=split["rgb"]), colour, background)
    if "depth" in outputs:
        safe_weights = torch.where(covered, blend.weight_sums, torch.ones_like(blend.weight_sums))
        depth = torch.where(covered, blend.depth_sums / safe_weights, torch.zeros_like(blend.depth_sums))
        if median_depth:  # depths are beyond the near plane, so 0 means "never below 1/2"
            depth = torch.where(blend.median_depth > 0, blend.median_depth.to(depth), depth)
        result.depth = depth
    if "alpha" in outputs:
        result.alpha = alpha
    if "features" in outputs:
        result.features = split["features"]
    if "labels" in outputs:
        scores, labelled = split["labels"][..., :-1], split["labels"][..., -1]
        # a pixel drawn mostly by Gaussians without label evidence (surfaces no labelled pixel saw) has none
        result.labels = torch.where(covered & (labelled >= 0.5 * blend.weight_sums), scores.argmax(-1), -1)
    return result

