"""Training data: captures at reduced resolution, fused scenes of sampled input views, and a
decode of their sums that gradients reach.

The fold (numba) is not differentiable and does not depend on the decoder, so each sampled set of
input views is folded once and its decodable fields are kept (`FusedSample`); a training step then
only decodes (the heads, in PyTorch) and renders. A sample is N input views (N drawn from
``views``) spread over a window of the capture and the frames between them as render targets, so
that targets are interpolated views as in the evaluation protocol (`eval.protocol`). A capture's
own evaluation held-out frames (the protocol's, for its N) are never inputs or targets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..datasets import UnknownLayout, load_dataset
from ..decode import GaussianDecoder, support_unit
from ..eval.protocol import interpolation_split
from ..eval.run import default_voxel_size
from ..frame import Frame, resize_frame
from ..gaussians import Gaussians
from ..scene import Scene, SceneConfig
from ..scene.fields import fields_from_sums

REPORT_VIEWS = 8  # N of the held-out report (inputs spread over the whole capture, as the protocol's)


@dataclass
class Capture:
    """One capture at training resolution: its frames, voxel size and the frames held out."""

    name: str
    frames: list[Frame]
    voxel_size: float
    heldout: tuple[int, ...]  # the protocol's held-out positions: never inputs or training targets
    report_inputs: tuple[int, ...]  # the protocol's inputs for `REPORT_VIEWS` views


EVALUATION_CAPTURE = "realsense_shelf"  # the folder name of the capture the decoder is evaluated on


class RefusedCapture(ValueError):
    """A path given as a training capture that cannot be one whatever its files hold: nothing is
    there, or it is the evaluation capture. The message starts with ``captures:``."""


def check_capture_path(path: str | Path) -> Path:
    """`RefusedCapture` unless ``path`` exists and is not the evaluation capture or inside it. The
    test is on the resolved path, so that ``.`` in the capture's folder, a symbolic link to it or a
    path through ``..`` is refused as its own name is."""
    path = Path(path)
    if not path.exists():
        raise RefusedCapture(f"captures: {path}: no such file or folder")
    resolved = path.resolve()
    if any(part.name == EVALUATION_CAPTURE for part in (resolved, *resolved.parents)):
        shown = str(path) if resolved == path else f"{path} ({resolved})"
        raise RefusedCapture(f"captures: {shown} is the evaluation capture; the decoder is never trained on it")
    return path


def _sequences(path: Path, **options) -> list:
    """The frame sequences of a capture folder; a folder whose subfolders each hold a capture (two
    bins of one rig) gives one sequence per subfolder. ``options``: `load_dataset`'s ``K`` and
    ``depth_scale``."""
    try:
        return [load_dataset(path, **options)]
    except UnknownLayout as exc:  # no capture there: the argument's fault, as a path with nothing there
        raise RefusedCapture(f"captures: {exc}") from None
    except ValueError as exc:
        subfolders = sorted(d for d in path.iterdir() if d.is_dir()) if path.is_dir() else []
        if "several subfolders" not in str(exc) or not subfolders:
            raise
        return [load_dataset(check_capture_path(d), **options) for d in subfolders]  # never the evaluation capture


def load_captures(paths: Sequence[str | Path], width: int = 160, K=None, depth_scale: float | None = None) -> list[Capture]:
    """Read every frame of the captures at ``paths``, resized to about ``width`` pixels across; ``K``
    and ``depth_scale`` go to `load_dataset` for every capture (intrinsics for a capture without an
    intrinsics file, depth units where they are not its layout's). All paths are checked
    (`check_capture_path`) before any is read."""
    if isinstance(width, bool) or not isinstance(width, int) or width < 32:
        raise ValueError(f"width: expected an integer of at least 32 pixels, got {width!r}")
    paths = [check_capture_path(p) for p in paths]
    captures = []
    for path in paths:
        for seq in _sequences(path, K=K, depth_scale=depth_scale):
            first = seq[0]
            scale = min(1.0, width / first.width)
            frames = [resize_frame(f, scale) for f in seq]
            if any(f.depth is None for f in frames):
                raise ValueError(f"captures: {seq.name} has frames without depth; training needs RGB-D captures")
            n = len(frames)
            views = [v for v in (2, 4, REPORT_VIEWS) if v <= n]
            split = _split(n, views)
            report = split.inputs[max(split.inputs)]
            captures.append(Capture(seq.name, frames, default_voxel_size([frames[p] for p in report]),
                                    split.heldout, report))
    return captures


def _split(n: int, views: list[int]):
    """The protocol's split with as many held-out frames (up to its 10) as a short capture leaves,
    dropping the largest view counts where it leaves none."""
    for k in range(len(views), 0, -1):
        for count in range(10, 0, -1):
            try:
                return interpolation_split(n, views[:k], heldout_count=count)
            except ValueError:
                continue
    raise ValueError(f"captures: {n} frames are too few to hold any frame out")


@dataclass
class FusedSample:
    """The decodable state of a scene fused from sampled inputs, and the frames to render."""

    capture: str
    fields: dict[str, Tensor]  # `fields_from_sums` of the rows the scene decodes
    support: Tensor  # [V] R_scene of those rows
    free: Tensor  # [V] their free-space evidence
    unit: float  # the scene's support unit (`decode.support_unit` x observations per view)
    voxel_size: float
    targets: list[Frame]


def scene_config(voxel_size: float) -> SceneConfig:
    """The settings training folds with: the defaults, and the training-free decoder."""
    return SceneConfig(voxel_size=voxel_size, model="none")


def fuse(frames: Sequence[Frame], voxel_size: float, targets: Sequence[Frame], name: str = "") -> FusedSample:
    """Fold ``frames`` and keep what a decode of the result reads: the rows `Scene.decode` keeps
    (support above 0, free-space evidence within `FreeSpace.dominance` of it) and their fields."""
    config = scene_config(voxel_size)
    scene = Scene(config)
    for frame in frames:
        scene.fold(frame)
    inputs = scene.decode_inputs()
    sums = inputs.sums
    support, free = torch.as_tensor(sums["r_sum"]), torch.as_tensor(sums["free"])
    unit = support_unit(support, torch.as_tensor(sums["n_obs"])) * inputs.observations_per_view
    keep = (support > 0) & (free <= config.free_space.dominance * support)
    rows = torch.nonzero(keep).squeeze(1)
    fields = fields_from_sums({k: torch.as_tensor(v).index_select(0, rows) for k, v in sums.items()}, config, sort=False)
    return FusedSample(name, fields, support[rows], free[rows], unit, voxel_size, list(targets))


def decode(decoder: GaussianDecoder, sample: FusedSample) -> Gaussians:
    """The Gaussians of ``sample`` as `Scene.decode` makes them, with gradients to the decoder."""
    opacities = decoder.opacities(sample.support, sample.free, sample.unit)
    return Gaussians(opacities=opacities, **decoder.shapes_and_colours(sample.fields, sample.voxel_size))


def draw_sample(capture: Capture, rng: np.random.Generator, views: Sequence[int] = (2, 4, 8, 16),
                targets: int = 2) -> tuple[list[int], list[int]]:
    """Input and target positions of one training sample: N (drawn from ``views``, at most what the
    capture allows) inputs at random over a window of 3 N frames, and ``targets`` frames between
    the first and last input that are neither inputs nor held out."""
    n = len(capture.frames)
    free = [p for p in range(n) if p not in set(capture.heldout)]
    count = int(rng.choice([v for v in views if v + targets <= len(free)] or [2]))
    span = min(len(free), 3 * count + targets)
    start = int(rng.integers(0, len(free) - span + 1))
    window = free[start: start + span]
    inputs = sorted(int(p) for p in rng.choice(window, size=count, replace=False))
    between = [p for p in window if inputs[0] < p < inputs[-1] and p not in inputs]
    chosen = rng.choice(between, size=min(targets, len(between)), replace=False) if between else []
    return inputs, sorted(int(p) for p in chosen) or [p for p in window if p not in inputs][:1]


def draw_pool(captures: Sequence[Capture], size: int, seed: int, views: Sequence[int] = (2, 4, 8, 16)) -> list[FusedSample]:
    """``size`` fused samples, round-robin over the captures, drawn with ``seed`` (deterministic)."""
    rng = np.random.default_rng(seed)
    pool = []
    for k in range(size):
        capture = captures[k % len(captures)]
        inputs, targets = draw_sample(capture, rng, views)
        pool.append(fuse([capture.frames[p] for p in inputs], capture.voxel_size,
                         [capture.frames[p] for p in targets], capture.name))
    return pool
