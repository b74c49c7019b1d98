"""`evaluate`: the whole protocol on one dataset -> results.json, results.md, plots and image grids.

Per method and number of input views N (inputs and held-out frames from `protocol`), every
held-out frame is rendered from the method's model and compared with its image (black background;
Gaussians in `render`'s "normalised" colour by default, each drawn pixel the expected colour of the
surface its ray hits, as a ray cast shows it; ``colour="composited"`` scores the 3DGS blend over
black instead):
PSNR over all pixels, PSNR over covered pixels (alpha >= 0.5), coverage, the all-pixel PSNR that
coverage allows (`coverage_ceiling`: covered pixels exact, the rest black), SSIM, depth agreement
(share of covered pixels whose rendered depth is within 2 voxels of the held-out frame's sensor
depth, where it has one: a floater measure), each the mean over the held-out frames; the number of
Gaussians; the build time (fold + decode for the scene methods) and the mean render time. Then the
same with depth noise on the inputs, the extrapolation split, and the feature-stability curve (mean
cosine of the feature splat from N views to the one from the reference, the largest stability N,
over pixels covered in both).

Depth noise: sigma = level x the frame's median valid depth, zero-mean Gaussian, added to valid
pixels; values that drop to <= 0 become missing. The generator of the frame at position p and
level l is seeded with (round(l * 1e6), p), so every method and every N sees the same noisy frame.
The mixed-quality run (``mixed_noise``) adds that noise to every other input view only.

Every group of runs on the same inputs also gets ``psnr_common``: PSNR over the pixels that every
method of the run covers (`add_common_psnr`), so that methods of unequal coverage are compared on
the same pixels; and the same split into ``psnr_edge`` (within 3 pixels of a depth edge or a hole
of the held-out frame's sensor depth) and ``psnr_flat`` (the rest).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple, get_args

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..datasets import FrameSequence, load_dataset
from ..frame import Frame, resize_frame
from ..rendering import Colour
from ..scene.choices import default_voxel_size
from .methods import METHODS, Model, build, check_methods, parse_method
from .metrics import DEPTH_TOLERANCE_VOXELS, cosine_map, coverage_ceiling, covered, coverage, depth_agreement, depth_edge_band, psnr, ssim
from .protocol import Split, extrapolation_split, interpolation_split, stability_inputs
from .figures import require_matplotlib
from .report import check_writable, write_partial_report, write_report


def add_depth_noise(frame: Frame, level: float, position: int) -> Frame:
    """Zero-mean Gaussian depth noise with sigma = ``level`` x the median valid depth (module docstring)."""
    if frame.depth is None:
        raise ValueError("depth: the noise protocol needs frames with depth")
    if not (isinstance(level, (int, float)) and math.isfinite(level) and level >= 0):
        raise ValueError(f"noise: expected non-negative levels, got {level!r}")
    if level == 0:
        return frame
    depth = frame.depth.numpy().astype(np.float64)
    valid = depth > 0
    if not valid.any():
        return frame
    sigma = level * float(np.median(depth[valid]))
    rng = np.random.default_rng([int(round(level * 1e6)), int(position)])
    noisy = np.where(valid, depth + sigma * rng.standard_normal(depth.shape), 0.0)
    return replace(frame, depth=np.where(noisy > 0, noisy, 0.0).astype(np.float32), depth_std=None)


def add_mixed_depth_noise(frames: Sequence[Frame], positions: Sequence[int], level: float) -> list[Frame]:
    """``frames`` (at sequence ``positions``) with `add_depth_noise` on every other one (the 2nd,
    4th, ...) and the rest as they are: inputs of uneven quality, the case reliability is for."""
    if len(frames) != len(positions):
        raise ValueError(f"positions: expected one per frame ({len(frames)}), got {len(positions)}")
    return [add_depth_noise(f, level, p) if k % 2 else f for k, (f, p) in enumerate(zip(frames, positions))]


def _positive_level(name: str, level) -> float:
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not (math.isfinite(level) and level > 0):
        raise ValueError(f"{name}: expected a positive level, got {level!r}")
    return float(level)


def _nanmean(values: Sequence[float]) -> float | None:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else None


class Scored(NamedTuple):
    """What `score` returns: the metrics, and per target the uint8 render and its covered pixels."""

    metrics: dict
    images: list[np.ndarray]  # [H, W, 3] uint8 per target
    covered: list[Tensor]  # [H, W] bool per target


def score(model: Model, targets: Sequence[Frame], voxel_size: float, colour: Colour = "normalised") -> Scored:
    """Metrics of ``model`` at the ``targets`` (means over targets), its renders and covered masks;
    Gaussians are rendered in ``colour`` mode (`rendering.render`)."""
    rows, images, masks = [], [], []
    for frame in targets:
        t0 = time.perf_counter()
        view = model.render(frame.camera, colour=colour)
        ms = (time.perf_counter() - t0) * 1000.0
        gt = frame.rgb.float() / 255.0
        agree = math.nan if frame.depth is None else depth_agreement(
            view.depth, view.alpha, frame.depth, DEPTH_TOLERANCE_VOXELS * voxel_size)
        masks.append(covered(view.alpha))
        rows.append((psnr(view.rgb, gt), psnr(view.rgb, gt, masks[-1]), coverage(view.alpha),
                     coverage_ceiling(view.alpha, gt, (view.alpha > 0) if colour == "normalised" else None),
                     ssim(view.rgb, gt), agree, ms))
        images.append((view.rgb.numpy() * 255.0 + 0.5).astype(np.uint8))
    p, pc, cov, ceiling, s, agree, ms = zip(*rows)
    metrics = {"psnr": float(np.mean(p)), "psnr_covered": _nanmean(pc), "coverage": float(np.mean(cov)),
               "psnr_ceiling": _nanmean([c if math.isfinite(c) else math.nan for c in ceiling]),
               "ssim": float(np.mean(s)), "depth_agreement": _nanmean(agree), "gaussians": model.gaussians,
               "render_ms": float(np.mean(ms))}
    return Scored(metrics, images, masks)


def add_common_psnr(runs: Sequence[dict], scored: Sequence[Scored], targets: Sequence[Frame]) -> None:
    """Give each of ``runs`` (one group: same inputs, every method) ``psnr_common``, its mean PSNR
    over the pixels that every run of the group covers, and ``common_coverage``, the share of
    pixels that is; and that PSNR split by the held-out frames' sensor depth (`depth_edge_band`):
    ``psnr_edge`` on the common pixels near a depth edge or a hole, ``psnr_flat`` on the rest, with
    ``edge_share``, the edge pixels' share of the common ones (None without sensor depth).

    Covered PSNR compares each method on its own pixels, and a method that draws only where it is
    sure (Open3D's TSDF, where few views see a surface) is scored on easier pixels; on the
    common pixels every method is judged on the same ones. The split tells speckle at depth edges
    (halos of the background's colour on the foreground's rim) from noisy flat surfaces. Computed
    from the 8-bit renders (their rounding moves PSNR by well under 0.01 dB at these error levels).
    """
    masks = [torch.stack([s.covered[k] for s in scored]).all(0) for k in range(len(targets))]
    share = float(np.mean([float(m.double().mean()) for m in masks]))
    truths = [t.rgb.float() / 255.0 for t in targets]  # once per group, not once per method
    edges = [None if t.depth is None else depth_edge_band(t.depth) for t in targets]
    edge_shares = [float((m & e).sum()) / max(int(m.sum()), 1) for m, e in zip(masks, edges) if e is not None]
    for run, s in zip(runs, scored):
        renders = [torch.from_numpy(image).float() / 255.0 for image in s.images]
        run["psnr_common"] = _nanmean([psnr(r, gt, m) for r, gt, m in zip(renders, truths, masks)])
        run["common_coverage"] = share
        for key, near in (("psnr_edge", True), ("psnr_flat", False)):
            run[key] = _nanmean([psnr(r, gt, m & (e if near else ~e))
                                 for r, gt, m, e in zip(renders, truths, masks, edges) if e is not None])
        run["edge_share"] = _nanmean(edge_shares)


def add_fixed_psnr(
    run: dict,
    scored: Scored,
    first_covered: list[Tensor],  # per target [H, W] bool: the method's covered pixels at the smallest N
    truths: Sequence[Tensor],  # per target [H, W, 3] colour in [0, 1]
) -> None:
    """Give ``run`` ``psnr_fixed``: its mean PSNR over the pixels that its method's run at the
    smallest N of the same condition covered (``first_covered``, per target) and this run still
    covers. Covered PSNR falls when added views draw new, harder pixels (far walls, grazing floors)
    even where the pixels already drawn got better; on this fixed set only the latter counts, which
    is the promise that more views make the scene better. From the 8-bit renders, as `add_common_psnr`.
    """
    values = [psnr(torch.from_numpy(image).float() / 255.0, truth, first & mask)
              for image, truth, first, mask in zip(scored.images, truths, first_covered, scored.covered)]
    run["psnr_fixed"] = _nanmean(values)


def stability(name: str, inputs: Mapping[int, Sequence[int]], frames: Mapping[int, Frame], targets: Sequence[Frame],
              voxel_size: float, bar: tqdm) -> list[dict]:
    """Mean cosine of the feature splat from each N to the reference (largest N) at the targets,
    pooled over the pixels covered in both renders."""
    def splat(n: int) -> list:
        model, _ = build(name, [frames[p] for p in inputs[n]], voxel_size, features=True)
        bar.set_postfix_str(f"stability {name} N={n}")
        bar.update()
        return [model.render(f.camera, features=True) for f in targets]

    counts = sorted(inputs)
    reference = splat(counts[-1])
    out = []
    for n in counts:
        views = reference if n == counts[-1] else splat(n)
        total, pixels = 0.0, 0
        for view, ref in zip(views, reference):
            mask = covered(view.alpha) & covered(ref.alpha)
            total += float(cosine_map(view.features, ref.features)[mask].sum())
            pixels += int(mask.sum())
        out.append({"method": name, "views": n, "cosine": total / pixels if pixels else None})
    return out


def evaluate(
    dataset: str | Path | FrameSequence,
    views: Sequence[int] = (2, 4, 8, 16),
    methods: Sequence[str] | None = None,
    noise: Sequence[float] = (),
    mixed_noise: float | None = None,
    out_dir: str | Path = "eval_out",
    progress: bool = True,
    scale: float = 1.0,
    voxel_size: float | None = None,
    stability_views: Sequence[int] | None = None,
    extrapolation: bool = True,
    colour: Colour = "normalised",
) -> dict:
    """Run the protocol (module docstring) and write results.json, results.md, PNG plots and image
    grids into ``out_dir``; returns the results dict (the JSON content). Interrupted (Ctrl-C), it
    writes the groups of runs finished so far, marked partial (`report.write_partial_report`), and
    raises KeyboardInterrupt again.

    Args:
        dataset: a path any loader reads (`load_dataset`), or a FrameSequence.
        views: input counts N.
        methods: names from `METHODS` (default: all), or a Scene method with settings
            (`methods.parse_method`: ``canonical:model=PATH``); ones that cannot run here are
            skipped with a note. Results name each by its label.
        noise: depth-noise levels (fractions of the median depth) besides the clean run.
        mixed_noise: a level for the mixed-quality run: noise on every other input view, the rest
            clean (evidence of uneven quality, which reliability weighting is for); None skips it.
        scale: image downscale factor in (0, 1] (for quick runs).
        voxel_size: voxel edge in the scene's unit; default `default_voxel_size` of the inputs.
        stability_views: input counts of the feature-stability curve (empty: skip it; None: those
            of `protocol.STABILITY_VIEWS` that the sequence has frames for). Counts given must fit (ValueError).
        extrapolation: also run the extrapolation split (when the sequence allows it).
        colour: how Gaussians' renders are scored, "normalised" or "composited" (`rendering.render`).
    """
    require_matplotlib()
    methods = check_methods(list(METHODS) if methods is None else methods)
    noise = sorted(set(_positive_level("noise", level) for level in noise))
    if mixed_noise is not None:
        mixed_noise = _positive_level("mixed_noise", mixed_noise)
    if voxel_size is not None and not voxel_size > 0:
        raise ValueError(f"voxel_size: expected a positive number, got {voxel_size!r}")
    if colour not in get_args(Colour):
        raise ValueError(f"colour: expected one of {list(get_args(Colour))}, got {colour!r}")
    sequence = dataset if isinstance(dataset, FrameSequence) else load_dataset(dataset)
    n = len(sequence)
    split = interpolation_split(n, views)
    extra: Split | None = extrapolation_split(n, views, split.heldout) if extrapolation else None
    resolved = {m: parse_method(m).method() for m in methods}
    skipped = {m: reason for m in methods if (reason := resolved[m].unavailable())}
    runnable = [m for m in methods if m not in skipped]
    feature_methods = [m for m in runnable if resolved[m].features]
    stab = stability_inputs(n, split.heldout, stability_views)  # checked even when no method has features
    stab = stab if feature_methods else {}
    stab_methods = feature_methods if stab else []
    out_dir = check_writable(out_dir)  # once the arguments are known good, before the runs take their minutes

    input_sets = [*split.inputs.values(), *(extra.inputs.values() if extra else ()), *stab.values()]
    positions = sorted(set(split.heldout).union(*input_sets))
    frames = {p: resize_frame(sequence[p], scale) for p in positions}
    targets = [frames[p] for p in split.heldout]
    if voxel_size is None:
        voxel_size = default_voxel_size([frames[p] for p in split.inputs[max(split.inputs)]])

    grid_at = sorted({0, len(targets) // 2, len(targets) - 1})
    grid_targets = [split.heldout[i] for i in grid_at]
    grids: dict[int, dict[str, list[np.ndarray]]] = {
        n_views: {"ground truth": [targets[i].rgb.numpy() for i in grid_at]} for n_views in split.inputs}

    groups = 1 + len(noise) + (mixed_noise is not None) + (extra is not None)
    steps = len(runnable) * len(split.inputs) * groups + len(stab_methods) * len(stab)
    bar = tqdm(total=steps, disable=not progress, file=sys.stderr, desc="eval", unit="run", dynamic_ncols=True)
    if progress:
        bar.write(f"{sequence.name}: {n} frames, voxel {voxel_size:g}, held out {list(split.heldout)}")
    truths = [t.rgb.float() / 255.0 for t in targets]  # once, for every run's fixed-pixel PSNR
    for name in runnable:  # warm-up: JIT compilation and caches stay out of the timings
        build(name, [frames[split.inputs[min(split.inputs)][0]]], voxel_size)[0].render(targets[0].camera)

    def run_group(inputs: Sequence[Frame], n_views: int, first_covered: dict[str, list[Tensor]], level: float = 0.0,
                  keep_grid: bool = False) -> list[dict]:
        """Every method on the same inputs, then the PSNR on the pixels all of them cover, and each
        one's on the pixels it covered at the condition's smallest N (``first_covered``: the
        condition's groups run from the smallest N up; the first one fills it)."""
        runs, scored = [], []
        for name in runnable:
            model, build_ms = build(name, inputs, voxel_size)
            scored.append(score(model, targets, voxel_size, colour))
            metrics = scored[-1].metrics
            bar.set_postfix_str(f"{name} N={n_views} noise={level:g}: {metrics['psnr']:.2f} dB")
            bar.update()
            if keep_grid:
                grids[n_views][name] = [scored[-1].images[i] for i in grid_at]
            runs.append({"method": name, "views": n_views, "noise": level, **metrics, "fold_ms": build_ms})
            add_fixed_psnr(runs[-1], scored[-1], first_covered.setdefault(name, scored[-1].covered), truths)
        add_common_psnr(runs, scored, targets)
        return runs

    runs, mixed_runs, extrapolation_runs, stability_rows = [], [], [], []
    try:  # Ctrl-C: the groups finished so far are written as partial results, then the interrupt goes on
        for level in [0.0, *noise]:
            noisy = {p: add_depth_noise(frames[p], level, p) for p in set().union(*split.inputs.values())}
            first: dict[str, list[Tensor]] = {}
            for n_views, inputs in sorted(split.inputs.items()):
                runs += run_group([noisy[p] for p in inputs], n_views, first, level, keep_grid=level == 0)
        first = {}
        for n_views, inputs in sorted(split.inputs.items()) if mixed_noise is not None else ():
            mixed_runs += run_group(add_mixed_depth_noise([frames[p] for p in inputs], inputs, mixed_noise), n_views,
                                    first, mixed_noise)
        first = {}
        for n_views, inputs in sorted(extra.inputs.items() if extra else ()):
            extrapolation_runs += run_group([frames[p] for p in inputs], n_views, first)
        for name in stab_methods:
            stability_rows += stability(name, stab, frames, targets, voxel_size, bar)
        interrupted = False
    except KeyboardInterrupt:
        interrupted = True
    bar.close()

    results = {
        "dataset": sequence.name,
        "frames": n,
        "frame_ids": sequence.frame_ids,
        "image_size": [targets[0].width, targets[0].height],
        "scale": scale,
        "voxel_size": voxel_size,
        "colour": colour,
        "heldout": list(split.heldout),
        "heldout_ids": [sequence.frame_ids[p] for p in split.heldout],
        "inputs": {str(k): list(v) for k, v in split.inputs.items()},
        "methods": runnable,
        "skipped": skipped,
        "noise_levels": noise,
        "runs": runs,
        "mixed_noise": None if mixed_noise is None else {"level": mixed_noise, "runs": mixed_runs},
        "extrapolation": None if extra is None else {
            "inputs": {str(k): list(v) for k, v in extra.inputs.items()},
            "span_ratio": {str(k): extra.span_ratio(k) for k in extra.inputs},
            "runs": extrapolation_runs,
        },
        "stability_inputs": {str(k): list(v) for k, v in stab.items()},
        "stability": stability_rows,
        "grid_heldout": grid_targets,
    }
    if interrupted:
        write_partial_report({**results, "partial": True}, out_dir)
        raise KeyboardInterrupt
    write_report(results, grids, out_dir)
    return results
